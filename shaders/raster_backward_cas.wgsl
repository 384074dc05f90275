// Backward of the rasteriser's blending for devices without f32 atomics: each add is a
// compare-and-swap loop on the value's bits. The kernel itself:
// shaders/include/raster_backward_body.wgsl.

// Per Gaussian: du, dv, conic a, b, c, opacity, r, g, b, depth.
@group(0) @binding(8) var<storage, read_write> grads: array<atomic<u32>>;

fn grad_add(i: u32, v: f32) {
    if (v == 0.0) {
        return;
    }
    var old = atomicLoad(&grads[i]);
    loop {
        let swapped = atomicCompareExchangeWeak(&grads[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (swapped.exchanged) {
            break;
        }
        old = swapped.old_value;
    }
}

// @include raster_backward_body.wgsl
