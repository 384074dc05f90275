// Row gather on rows whose width is a multiple of 4, a vec4 a step: `gather.wgsl`'s `main` (see
// there: out[r] = src[idx[r]], plus base[r] when `add` is set; an index past the source's rows
// yields zeros) for CPU devices, where every storage access is a loop over the SIMD lanes and a
// vec4 costs about twice a scalar (docs/decisions/kernels.md). `width` counts vec4s here.
// Host side engine/src/ops/gather.rs.

struct Params {
    rows: u32,     // rows of out (= length of idx)
    width: u32,    // vec4s a row
    src_rows: u32,
    add: u32,
}

@group(0) @binding(0) var<storage, read> src: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> idx: array<u32>;
@group(0) @binding(2) var<storage, read_write> out: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> base: array<vec4<f32>>;
var<immediate> pc: Params;

// @include elements.wgsl

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.rows * pc.width; i += element_stride(nwg)) {
        let r = i / pc.width;
        let s = idx[r];
        var v = vec4<f32>(0.0);
        if (s < pc.src_rows) {
            v = src[s * pc.width + (i - r * pc.width)];
        }
        if (pc.add != 0u) {
            v += base[i];
        }
        out[i] = v;
    }
}
