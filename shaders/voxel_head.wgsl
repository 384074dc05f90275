// The voxel decoder's head (models/src/velox/voxels.rs): a cell's hidden vector a_c, plus the
// embedding b_v of a voxel's offset within the cell, plus (with cell directions) the offset's
// components along three learned directions m_c,k, through a GELU:
//   pre[c, v, j] = a[c, j] + b[v, j] + sum_k m[c, k, j] o[v, k],   act = gelu(pre)
// with features[c] = a[c] (++ m[c, 0] ++ m[c, 1] ++ m[c, 2] with directions). `forward`
// writes pre and act in one pass over [cells, per, h] (it took seven broadcast passes and a
// GELU pass); `backward` writes the features' gradient from dpre = dL/dpre, one invocation
// per output summing over the cell's voxels: d a[c, j] = sum_v dpre[c, v, j] and
// d m[c, k, j] = sum_v dpre[c, v, j] o[v, k].

struct Params {
    cells: u32,
    per: u32,       // voxels per cell
    h: u32,         // hidden width
    directions: u32,
}

@group(0) @binding(0) var<storage, read> features: array<f32>;        // [cells, F], F = h or 4 h
@group(0) @binding(1) var<storage, read> embedded: array<f32>;        // [per, h]
@group(0) @binding(2) var<storage, read> offsets: array<f32>;         // [per, 3]
@group(0) @binding(3) var<storage, read_write> pre: array<f32>;       // [cells, per, h]
@group(0) @binding(4) var<storage, read_write> act: array<f32>;       // [cells, per, h]
@group(0) @binding(5) var<storage, read> dpre: array<f32>;            // [cells, per, h]
@group(0) @binding(6) var<storage, read_write> dfeatures: array<f32>; // [cells, F]
var<immediate> pc: Params;

// @include gelu_fn.wgsl

fn width() -> u32 {
    return select(pc.h, 4u * pc.h, pc.directions != 0u);
}

@compute @workgroup_size(256)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let i = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (i >= pc.cells * pc.per * pc.h) {
        return;
    }
    let j = i % pc.h;
    let v = (i / pc.h) % pc.per;
    let c = i / (pc.h * pc.per);
    let row = c * width();
    var x = features[row + j] + embedded[v * pc.h + j];
    if (pc.directions != 0u) {
        for (var k = 0u; k < 3u; k++) {
            x += features[row + (k + 1u) * pc.h + j] * offsets[v * 3u + k];
        }
    }
    pre[i] = x;
    act[i] = gelu(x);
}

@compute @workgroup_size(256)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let o = (wid.x + wid.y * nwg.x) * 256u + lid;
    let f = width();
    if (o >= pc.cells * f) {
        return;
    }
    let c = o / f;
    let k = (o % f) / pc.h; // 0: a; 1 to 3: the directions
    let j = o % pc.h;
    var sum = 0.0;
    for (var v = 0u; v < pc.per; v++) {
        let d = dpre[(c * pc.per + v) * pc.h + j];
        if (k == 0u) {
            sum += d;
        } else {
            sum += d * offsets[v * 3u + k - 1u];
        }
    }
    dfeatures[o] = sum;
}
