// f32 <-> f16 conversion. f16 tensors are read and written as packed pairs in u32 words
// (pack2x16float / unpack2x16float), so the conversion needs neither 16-bit storage nor f16
// arithmetic and runs on every device. Each invocation handles one word (two halves); an odd
// tail keeps the upper half of the last word at zero.

struct Params {
    n: u32, // number of elements
}

@group(0) @binding(0) var<storage, read> src_f32: array<f32>;
@group(0) @binding(1) var<storage, read_write> dst_f16: array<u32>;
@group(0) @binding(2) var<storage, read> src_f16: array<u32>;
@group(0) @binding(3) var<storage, read_write> dst_f32: array<f32>;
var<immediate> pc: Params;

@compute @workgroup_size(256)
fn f32_to_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let w = (wid.x + wid.y * nwg.x) * 256u + lid;
    let i = 2u * w;
    if (i >= pc.n) {
        return;
    }
    var hi = 0.0;
    if (i + 1u < pc.n) {
        hi = src_f32[i + 1u];
    }
    dst_f16[w] = pack2x16float(vec2<f32>(src_f32[i], hi));
}

@compute @workgroup_size(256)
fn f16_to_f32(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    let w = (wid.x + wid.y * nwg.x) * 256u + lid;
    let i = 2u * w;
    if (i >= pc.n) {
        return;
    }
    let v = unpack2x16float(src_f16[w]);
    dst_f32[i] = v.x;
    if (i + 1u < pc.n) {
        dst_f32[i + 1u] = v.y;
    }
}
