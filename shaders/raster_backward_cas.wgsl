// Backward of the rasteriser's blending for devices without f32 atomics: each add is a
// compare-and-swap loop on the value's bits (otherwise `raster_backward_atomic.wgsl`, and as
// there, the order of the adds varies between runs). The kernel itself:
// shaders/include/raster_backward_body.wgsl.

// Per Gaussian: du, dv, conic a, b, c, opacity, r, g, b, depth.
@group(0) @binding(8) var<storage, read_write> grads: array<atomic<u32>>;

// `init_grads` and `flush_grads` do nothing here: one chunk per batch.
fn init_grads(lid: u32) {}

fn chunk_size(nsg: u32) -> u32 {
    return BATCH;
}

fn grad_add(i: u32, v: f32) {
    var old = atomicLoad(&grads[i]);
    loop {
        let swapped = atomicCompareExchangeWeak(&grads[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (swapped.exchanged) {
            break;
        }
        old = swapped.old_value;
    }
}

fn store_grad(sg: u32, nsg: u32, lane: u32, j: u32, gaussian: u32, c: u32, sum: f32) {
    if (lane == 0u && sum != 0.0) {
        grad_add(10u * gaussian + c, sum);
    }
}

fn flush_grads(lid: u32, chunk: u32, nsg: u32, entry: u32) {}

// @include raster_backward_body.wgsl
