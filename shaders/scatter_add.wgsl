// Row scatter-add with native f32 atomics (VK_EXT_shader_atomic_float); `scatter_add_cas.wgsl`
// is the fallback for devices without them. The kernel is in include/scatter_add_body.wgsl.

@group(0) @binding(2) var<storage, read_write> out: array<atomic<f32>>;

fn add_at(j: u32, v: f32) {
    atomicAdd(&out[j], v);
}

// @include scatter_add_body.wgsl
