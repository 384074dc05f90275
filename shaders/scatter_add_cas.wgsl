// Row scatter-add for devices without f32 atomics: the same contract as `scatter_add.wgsl`,
// with the add done by a compare-and-swap loop on the value's bits.

struct Params {
    rows: u32,
    width: u32,
    dst_rows: u32,
}

@group(0) @binding(0) var<storage, read> src: array<f32>;
@group(0) @binding(1) var<storage, read> idx: array<u32>;
@group(0) @binding(2) var<storage, read_write> out: array<atomic<u32>>;
var<immediate> pc: Params;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let i = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (i >= pc.rows * pc.width) {
        return;
    }
    let r = i / pc.width;
    let c = i - r * pc.width;
    let d = idx[r];
    if (d >= pc.dst_rows) {
        return;
    }
    let v = src[i];
    let j = d * pc.width + c;
    var old = atomicLoad(&out[j]);
    loop {
        let swapped = atomicCompareExchangeWeak(&out[j], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (swapped.exchanged) {
            break;
        }
        old = swapped.old_value;
    }
}
