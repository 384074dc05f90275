// Fills a buffer with one 32-bit word (f32, u32, i32, or two f16 halves packed).

struct Params {
    words: u32,
    value: u32,
}

@group(0) @binding(0) var<storage, read_write> data: array<u32>;
var<immediate> pc: Params;

// @include elements.wgsl

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.words; i += element_stride(nwg)) {
        data[i] = pc.value;
    }
}
