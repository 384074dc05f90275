// Row scatter-add, shared by `scatter_add.wgsl` (native f32 atomics) and `scatter_add_cas.wgsl`
// (compare-and-swap), which each define the `out` binding and `add_at(index, value)`:
// out[idx[r], c] += src[r, c]. Indices past the destination's rows are skipped.

struct Params {
    rows: u32,     // rows of src (= length of idx)
    width: u32,
    dst_rows: u32,
    _add: u32,     // the gather's flag (the two share their push constants), unused here
}

@group(0) @binding(0) var<storage, read> src: array<f32>;
@group(0) @binding(1) var<storage, read> idx: array<u32>;
var<immediate> pc: Params;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let i = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (i >= pc.rows * pc.width) {
        return;
    }
    let r = i / pc.width;
    let c = i - r * pc.width;
    let d = idx[r];
    if (d < pc.dst_rows) {
        add_at(d * pc.width + c, src[i]);
    }
}
