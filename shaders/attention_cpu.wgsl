// @variants D: 16 32 64 72
// Fused segment attention for CPU devices, forward and backward, on f32 q, k and v: the
// kernels of `include/attention_cpu_body.wgsl` (see there), in place of `attention.wgsl`'s
// where the device is a CPU (`Caps::cpu_kernels`); the same bindings, push constants and
// outputs. Host side engine/src/ops/attention.rs.

const D: u32 = 32u;
const D4: u32 = D / 4u;

@group(0) @binding(0) var<storage, read> q: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> k: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> v: array<vec4<f32>>;

fn load_q(i: u32) -> vec4<f32> {
    return q[i];
}

fn load_k(i: u32) -> vec4<f32> {
    return k[i];
}

fn load_v(i: u32) -> vec4<f32> {
    return v[i];
}

// @include attention_cpu_body.wgsl
