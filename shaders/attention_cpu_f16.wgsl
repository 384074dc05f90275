// @variants D: 16 32 64 72
// Fused segment attention for CPU devices on f16 q, k and v (two halves to a 32-bit word,
// unpacked to f32 as in `attention_f16.wgsl`): the kernels of
// `include/attention_cpu_body.wgsl`, in place of `attention_f16.wgsl`'s where the device is a
// CPU. Everything after the loads is f32, as there.

const D: u32 = 32u;
const D4: u32 = D / 4u;

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

// @include attention_cpu_body.wgsl
