// Row scatter-add for devices without f32 atomics: the contract of `scatter_add.wgsl`, with
// each add a compare-and-swap loop on the value's bits. The kernel is in
// include/scatter_add_body.wgsl.

@group(0) @binding(2) var<storage, read_write> out: array<atomic<u32>>;

fn add_at(j: u32, v: f32) {
    var old = atomicLoad(&out[j]);
    loop {
        let swapped = atomicCompareExchangeWeak(&out[j], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (swapped.exchanged) {
            break;
        }
        old = swapped.old_value;
    }
}

// @include scatter_add_body.wgsl
