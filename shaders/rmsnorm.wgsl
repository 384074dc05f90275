// @variants WG: 256 8
// RMSNorm over the last axis: y = x * rstd * w, rstd = 1 / sqrt(mean(x^2) + eps).
// `forward` and `backward` give each row `pc.lanes` invocations and reduce in workgroup memory
// (row_reduce.wgsl). `param_grads` gives each invocation one column and a chunk of rows
// and writes partial sums of dw = sum_rows dy * x * rstd, which the host reduces over chunks.
//
// Backward (xhat = x * rstd, g = dy * w):  dx = rstd * (g - xhat * mean(g * xhat)), plus `res`
// when `residual` is set (a pre-norm residual block's dx = dres + RMSNorm'(dy) in one pass).

struct Params {
    rows: u32,
    width: u32,
    eps: f32,
    rows_per_chunk: u32,
    lanes: u32,
    residual: u32,
}

@group(0) @binding(0) var<storage, read> x: array<f32>;
@group(0) @binding(1) var<storage, read> w: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;
@group(0) @binding(3) var<storage, read_write> rstd: array<f32>;
@group(0) @binding(4) var<storage, read> dy: array<f32>;
@group(0) @binding(5) var<storage, read_write> dx: array<f32>;
@group(0) @binding(6) var<storage, read_write> dw_part: array<f32>;
@group(0) @binding(7) var<storage, read> res: array<f32>;
var<immediate> pc: Params;

// @include row_reduce.wgsl

@compute @workgroup_size(WG)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let at = row_slot(wid, nwg, lid, pc.lanes, pc.rows);
    if (at.first_row >= pc.rows) {
        return;
    }
    let base = at.row * pc.width;
    let end = select(0u, pc.width, at.live);
    var ss = 0.0;
    for (var j = at.lane; j < end; j += pc.lanes) {
        let v = x[base + j];
        ss += v * v;
    }
    ss = reduce_sum(lid, pc.lanes, ss);
    let r = inverseSqrt(ss / f32(pc.width) + pc.eps);
    for (var j = at.lane; j < end; j += pc.lanes) {
        y[base + j] = x[base + j] * r * w[j];
    }
    if (at.live && at.lane == 0u) {
        rstd[at.row] = r;
    }
}

@compute @workgroup_size(WG)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let at = row_slot(wid, nwg, lid, pc.lanes, pc.rows);
    if (at.first_row >= pc.rows) {
        return;
    }
    let base = at.row * pc.width;
    let end = select(0u, pc.width, at.live);
    let r = select(0.0, rstd[min(at.row, pc.rows - 1u)], at.live);
    var dot = 0.0;
    for (var j = at.lane; j < end; j += pc.lanes) {
        dot += dy[base + j] * w[j] * x[base + j] * r;
    }
    let m = reduce_sum(lid, pc.lanes, dot) / f32(pc.width);
    for (var j = at.lane; j < end; j += pc.lanes) {
        let xhat = x[base + j] * r;
        var v = r * (dy[base + j] * w[j] - xhat * m);
        if (pc.residual != 0u) {
            v += res[base + j];
        }
        dx[base + j] = v;
    }
}

@compute @workgroup_size(64)
fn param_grads(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let col = wid.x * 64u + lid;
    if (col >= pc.width) {
        return;
    }
    let chunk = wid.y;
    let start = chunk * pc.rows_per_chunk;
    let end = min(start + pc.rows_per_chunk, pc.rows);
    var acc = 0.0;
    for (var r = start; r < end; r++) {
        let i = r * pc.width + col;
        acc += dy[i] * x[i] * rstd[r];
    }
    dw_part[chunk * pc.width + col] = acc;
}
