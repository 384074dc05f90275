// Backward of the rasteriser's blending with native f32 atomic adds (VK_EXT_shader_atomic_float);
// `raster_backward_cas.wgsl` is the same kernel for devices without them. The kernel itself:
// shaders/include/raster_backward_body.wgsl.

// Per Gaussian: du, dv, conic a, b, c, opacity, r, g, b, depth.
@group(0) @binding(8) var<storage, read_write> grads: array<atomic<f32>>;

fn grad_add(i: u32, v: f32) {
    if (v != 0.0) {
        atomicAdd(&grads[i], v);
    }
}

// @include raster_backward_body.wgsl
