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

// @include elements.wgsl

@compute @workgroup_size(256)
fn f32_to_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    for (var w = first_element(wid, nwg, lid); ; w += element_stride(nwg)) {
        let i = 2u * w;
        if (i >= pc.n) {
            break;
        }
        var hi = 0.0;
        if (i + 1u < pc.n) {
            hi = src_f32[i + 1u];
        }
        dst_f16[w] = pack_halves(vec2<f32>(src_f32[i], hi));
    }
}

// pack2x16float, with magnitudes that round past the largest half (65504; from 65520 on) made
// infinities of their sign as IEEE rounding gives: what packing does there is left to the
// device, and SwiftShader gives NaN.
fn pack_halves(v: vec2<f32>) -> u32 {
    var bits = pack2x16float(v);
    let inf = select(vec2<u32>(0x7c00u), vec2<u32>(0xfc00u), v < vec2<f32>(0.0));
    if (abs(v.x) >= 65520.0) {
        bits = (bits & 0xffff0000u) | inf.x;
    }
    if (abs(v.y) >= 65520.0) {
        bits = (bits & 0x0000ffffu) | (inf.y << 16u);
    }
    return bits;
}

@compute @workgroup_size(256)
fn f16_to_f32(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
              @builtin(local_invocation_index) lid: u32) {
    for (var w = first_element(wid, nwg, lid); ; w += element_stride(nwg)) {
        let i = 2u * w;
        if (i >= pc.n) {
            break;
        }
        let v = unpack2x16float(src_f16[w]);
        dst_f32[i] = v.x;
        if (i + 1u < pc.n) {
            dst_f32[i + 1u] = v.y;
        }
    }
}
