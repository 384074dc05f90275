// @variants D: 16 32 64 72
// Fused segment attention, forward and backward, on f16 q, k and v: the f16 model path's
// attention on every device. The algorithm, layouts and outputs are those of `attention.wgsl`
// (see there); only the inputs differ. They are stored two halves to a 32-bit word, so four
// features are one vec2<u32>, unpacked to f32 by unpack2x16float (no 16-bit device feature
// needed); scores, softmax statistics, the output and the gradients accumulate in f32, and o,
// lse, dq, dk and dv are f32.

const D: u32 = 32u;
const D4: u32 = D / 4u;
const B: u32 = 32u; // rows per work item, and rows per staged tile

@group(0) @binding(0) var<storage, read> q: array<vec2<u32>>;
@group(0) @binding(1) var<storage, read> k: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> v: array<vec2<u32>>;

fn unpack4(w: vec2<u32>) -> vec4<f32> {
    return vec4<f32>(unpack2x16float(w.x), unpack2x16float(w.y));
}

fn load_q(i: u32) -> vec4<f32> {
    return unpack4(q[i]);
}

fn load_k(i: u32) -> vec4<f32> {
    return unpack4(k[i]);
}

fn load_v(i: u32) -> vec4<f32> {
    return unpack4(v[i]);
}

// @include attention_forward.wgsl
// @include attention_backward.wgsl
