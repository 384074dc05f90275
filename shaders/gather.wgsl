// Row gather: out[r, c] = src[idx[r], c] (plus base[r, c] when `add` is set: a residual added in
// the same pass). An index past the source's rows yields zeros, so a bad index can never read
// outside the buffer.

struct Params {
    rows: u32,     // rows of out (= length of idx)
    width: u32,
    src_rows: u32,
    add: u32,
}

@group(0) @binding(0) var<storage, read> src: array<f32>;
@group(0) @binding(1) var<storage, read> idx: array<u32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;
@group(0) @binding(3) var<storage, read_write> inverse: array<u32>;
@group(0) @binding(4) var<storage, read> base: array<f32>;
var<immediate> pc: Params;

// @include elements.wgsl

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.rows * pc.width; i += element_stride(nwg)) {
        let r = i / pc.width;
        let c = i - r * pc.width;
        let s = idx[r];
        var v = 0.0;
        if (s < pc.src_rows) {
            v = src[s * pc.width + c];
        }
        if (pc.add != 0u) {
            v += base[i];
        }
        out[i] = v;
    }
}

// The inverse of a permutation: inverse[idx[i]] = i for i < rows (`rows` = its length).
// Entries past the end are skipped, so a bad index cannot write outside the buffer.
@compute @workgroup_size(256)
fn invert(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
          @builtin(local_invocation_index) lid: u32) {
    let i = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (i >= pc.rows) {
        return;
    }
    let j = idx[i];
    if (j < pc.rows) {
        inverse[j] = i;
    }
}
