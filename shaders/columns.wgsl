// Column blocks of row-major matrices: dst[r, dst_col + j] = scale * src[r, src_col + j] for
// j < count. Builds feature matrices from pieces (xyz, rgb, Fourier features) and 4D points
// (x, y, z, tau * time_scale) from the 7-channel cloud, without a host round trip.

struct Params {
    rows: u32,
    count: u32,
    src_width: u32,
    src_col: u32,
    dst_width: u32,
    dst_col: u32,
    scale: f32,
}

@group(0) @binding(0) var<storage, read> src: array<f32>;
@group(0) @binding(1) var<storage, read_write> dst: array<f32>;
var<immediate> pc: Params;

// @include elements.wgsl

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.rows * pc.count; i += element_stride(nwg)) {
        let r = i / pc.count;
        let j = i - r * pc.count;
        dst[r * pc.dst_width + pc.dst_col + j] = pc.scale * src[r * pc.src_width + pc.src_col + j];
    }
}
