// Backward of the rasteriser's blending with native f32 atomic adds (VK_EXT_shader_atomic_float):
// each subgroup's lane 0 adds its sums to the Gaussian's ten gradients. The order of the adds
// depends on scheduling, so the last bits of the sums vary between runs; `raster_backward.wgsl`
// is the deterministic kernel that training uses. `raster_backward_cas.wgsl` is this kernel for
// devices without f32 atomics. The kernel itself: shaders/include/raster_backward_body.wgsl.

// Per Gaussian: du, dv, conic a, b, c, opacity, r, g, b, depth.
@group(0) @binding(8) var<storage, read_write> grads: array<atomic<f32>>;

// `init_grads` and `flush_grads` do nothing here: one chunk per batch.
fn init_grads(lid: u32) {}

fn chunk_size(nsg: u32) -> u32 {
    return BATCH;
}

fn store_grad(sg: u32, nsg: u32, lane: u32, j: u32, gaussian: u32, c: u32, sum: f32) {
    if (lane == 0u && sum != 0.0) {
        atomicAdd(&grads[10u * gaussian + c], sum);
    }
}

fn flush_grads(lid: u32, chunk: u32, nsg: u32, entry: u32) {}

// @include raster_backward_body.wgsl
