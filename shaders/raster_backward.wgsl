// Backward of the rasteriser's blending, deterministic: the same inputs give the same bits on
// every run, whatever the scheduling. The kernel itself: shaders/include/raster_backward_body.wgsl.
//
// `main`: within a tile, each subgroup's sums for a chunk of Gaussians go to its own corner of
// workgroup memory; after the chunk, one invocation per (Gaussian, channel) adds the
// subgroups' sums in subgroup order and writes the total to the pair's slot in `pair_grads`
// (no atomics: a (tile, Gaussian) pair belongs to one workgroup). Slots group each
// Gaussian's pairs (engine/src/ops/raster/forward.rs), so
// `sum_pairs`: one invocation per Gaussian adds its pairs' gradients in slot order (its tiles in
// row order) into its ten image-space gradients.
//
// Workgroup memory: the batch staging of the body (13 KiB) and PART_FLOATS (10 KiB) for the
// subgroups' sums, within lavapipe's 32 KiB. A chunk is as many Gaussians as those floats hold
// for the workgroup's subgroups, so there are two barriers per 8 Gaussians with subgroups of 8
// (lavapipe: 32 subgroups), per 32 with subgroups of 32 (NVIDIA), and one Gaussian a chunk at
// worst (subgroups of one invocation).

// Per pair slot: du, dv, conic a, b, c, opacity, r, g, b, depth (zeroed by the host first).
@group(0) @binding(8) var<storage, read_write> pair_grads: array<f32>;
// The slot of each sorted pair.
@group(0) @binding(9) var<storage, read> slots: array<u32>;
// `sum_pairs`: each Gaussian's pair count and first slot, and its summed gradients.
@group(0) @binding(10) var<storage, read> counts: array<u32>;
@group(0) @binding(11) var<storage, read> offsets: array<u32>;
@group(0) @binding(12) var<storage, read_write> grad2d: array<f32>;

const PART_FLOATS: u32 = 2560u;
const MAX_CHUNK: u32 = 64u;

// The sums of subgroup `sg` for the chunk's j-th Gaussian are s_part[(j nsg + sg) 10 + c]; a
// subgroup that did not touch that Gaussian leaves its zeros.
var<workgroup> s_part: array<f32, PART_FLOATS>;

fn init_grads(lid: u32) {
    for (var i = lid; i < PART_FLOATS; i = i + 256u) {
        s_part[i] = 0.0;
    }
}

fn chunk_size(nsg: u32) -> u32 {
    return clamp(PART_FLOATS / (10u * nsg), 1u, MAX_CHUNK);
}

fn store_grad(sg: u32, nsg: u32, lane: u32, j: u32, gaussian: u32, c: u32, sum: f32) {
    if (lane == 0u) {
        s_part[(j * nsg + sg) * 10u + c] = sum;
    }
}

// One invocation per (Gaussian, channel) adds the subgroups' sums in subgroup order, zeroing
// them for the next chunk, and writes the total to the pair's slot.
fn flush_grads(lid: u32, chunk: u32, nsg: u32, entry: u32) {
    workgroupBarrier();
    for (var i = lid; i < chunk * 10u; i = i + 256u) {
        let j = i / 10u;
        let c = i % 10u;
        var v = 0.0;
        for (var s = 0u; s < nsg; s = s + 1u) {
            let at = (j * nsg + s) * 10u + c;
            v = v + s_part[at];
            s_part[at] = 0.0;
        }
        pair_grads[10u * slots[entry - j] + c] = v;
    }
    workgroupBarrier();
}

// @include raster_backward_body.wgsl

@compute @workgroup_size(256)
fn sum_pairs(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
             @builtin(local_invocation_index) lid: u32) {
    let g = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (g >= pc.gaussians) {
        return;
    }
    var acc = array<f32, 10>(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    // Slots past the lists' room belong to pairs that were dropped (a step sized ahead that
    // overflowed, whose update the device vetoes): never read out of bounds.
    let first = offsets[g];
    let end = min(first + counts[g], pc.pairs);
    for (var s = first; s < end; s = s + 1u) {
        for (var c = 0u; c < 10u; c = c + 1u) {
            acc[c] = acc[c] + pair_grads[10u * s + c];
        }
    }
    for (var c = 0u; c < 10u; c = c + 1u) {
        grad2d[10u * g + c] = acc[c];
    }
}
