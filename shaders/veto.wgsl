// Vetoes a step on the device: when `count[0]` exceeds `limit`, writes +Inf over `norm[0]`
// (a gradient norm, as raw bits), and the AdamW kernel, which skips its step on a non-finite
// norm (adamw.wgsl), leaves the parameters and moments as they were. For work sized ahead of
// a count the device computes in the same recording (the rasteriser's tile lists, sized from
// earlier steps): the host learns of the overflow after the submission, when the update has
// been recorded already, and runs the step again with room enough.

struct Params {
    limit: u32,
    pad: u32,
}

@group(0) @binding(0) var<storage, read> count: array<u32>;
@group(0) @binding(1) var<storage, read_write> norm: array<u32>;
var<immediate> pc: Params;

@compute @workgroup_size(1)
fn main() {
    if (count[0] > pc.limit) {
        norm[0] = 0x7f800000u;
    }
}
