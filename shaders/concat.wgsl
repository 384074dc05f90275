// Concatenation of index lists (host side: engine/src/ops/concat.rs): dst[dst_start + i] =
// src[src_start + i] + add for i < count. Batched layouts build their index lists (points,
// queries, window ids) per sample and shift each into the batch's numbering with it.

struct Params {
    src_start: u32,
    dst_start: u32,
    count: u32,
    add: u32,
}

@group(0) @binding(0) var<storage, read> src: array<u32>;
@group(0) @binding(1) var<storage, read_write> dst: array<u32>;
var<immediate> pc: Params;

// @include elements.wgsl

@compute @workgroup_size(256)
fn copy_add(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    for (var i = first_element(wid, nwg, lid); i < pc.count; i += element_stride(nwg)) {
        dst[pc.dst_start + i] = src[pc.src_start + i] + pc.add;
    }
}
