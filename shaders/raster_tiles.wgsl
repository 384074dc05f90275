// Tile lists of the rasteriser (host side: engine/src/ops/raster/forward.rs).
//
// Every (tile, Gaussian) pair has a slot: Gaussian g's pairs fill slots offsets[g] ..
// offsets[g] + counts[g] (the exclusive scan of the tile counts), its rectangle's tiles in row
// order. The pairs are put in blending order (by tile, front to back within a tile, equal
// depths in Gaussian order) with one sort of the Gaussians and one of the pairs:
// - `depths`: one invocation per Gaussian writes its full 32-bit depth (its f32 pattern, which
//   orders like the depth since depths are positive);
// - the host sorts the Gaussians by depth, stably (N items, not pairs): `order`;
// - `counts_in_depth_order` lists the tile counts in that order, and the host scans them into
//   each Gaussian's first place in depth order;
// - `emit`: one invocation per Gaussian, in depth order, writes its pairs' tiles and slots
//   from that place on, so the pairs stand in depth order, and each slot's Gaussian;
// - the host sorts (tile, slot) on the tile bits, stably, so depth order survives within a
//   tile;
// - `ranges_of_tiles` marks where each tile's run starts and ends, and names the Gaussian of
//   every sorted pair.
// The sorted slots are kept for the backward pass, which writes its per-pair gradients by slot
// so that each Gaussian's lie together and are summed in a fixed order.

struct Params {
    n: u32,          // Gaussians (depths, counts_in_depth_order, emit) or pairs (ranges_of_tiles)
    tiles_x: u32,
    // emit: pairs the buffers hold (pairs past it are dropped, never written out of bounds);
    // ranges: the number of tiles (keys of other tiles are ignored).
    limit: u32,
    pad: u32,
}

@group(0) @binding(0) var<storage, read> counts: array<u32>;
@group(0) @binding(1) var<storage, read> offsets: array<u32>;
@group(0) @binding(2) var<storage, read> rects: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> proj: array<vec4<f32>>;
// Per Gaussian: its depth bits; the Gaussians in depth order; their counts and first places
// in that order.
@group(0) @binding(4) var<storage, read_write> depth_keys: array<u32>;
@group(0) @binding(5) var<storage, read> order: array<u32>;
@group(0) @binding(6) var<storage, read_write> ordered_counts: array<u32>;
@group(0) @binding(7) var<storage, read> ordered_offsets: array<u32>;
// Per pair in depth order: its tile and slot (the values the tile sort carries); per slot,
// its Gaussian.
@group(0) @binding(8) var<storage, read_write> tile_keys: array<u32>;
@group(0) @binding(9) var<storage, read_write> pair_slots: array<u32>;
@group(0) @binding(10) var<storage, read_write> slot_gaussians: array<u32>;
// The final order: each pair's tile and slot; per tile the first pair and one past the last;
// the Gaussian of each pair.
@group(0) @binding(11) var<storage, read> sorted_tiles: array<u32>;
@group(0) @binding(12) var<storage, read> sorted_slots: array<u32>;
@group(0) @binding(13) var<storage, read_write> ranges: array<u32>;
@group(0) @binding(14) var<storage, read_write> ids: array<u32>;
var<immediate> pc: Params;

fn linear_id(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return (wid.x + wid.y * nwg.x) * 256u + lid;
}

@compute @workgroup_size(256)
fn depths(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
          @builtin(local_invocation_index) lid: u32) {
    let g = linear_id(wid, nwg, lid);
    if (g >= pc.n) {
        return;
    }
    // A Gaussian without tiles emits nothing; it goes last.
    depth_keys[g] = select(bitcast<u32>(proj[3u * g].z), 0xffffffffu, counts[g] == 0u);
}

@compute @workgroup_size(256)
fn counts_in_depth_order(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                         @builtin(local_invocation_index) lid: u32) {
    let r = linear_id(wid, nwg, lid);
    if (r >= pc.n) {
        return;
    }
    ordered_counts[r] = counts[min(order[r], pc.n - 1u)];
}

@compute @workgroup_size(256)
fn emit(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let r = linear_id(wid, nwg, lid);
    if (r >= pc.n) {
        return;
    }
    let g = min(order[r], pc.n - 1u);
    if (counts[g] == 0u) {
        return;
    }
    let rect = rects[g];
    let x0 = rect.x & 0xffffu;
    let y0 = rect.x >> 16u;
    let x1 = rect.y & 0xffffu;
    let y1 = rect.y >> 16u;
    var at = ordered_offsets[r];
    var slot = offsets[g];
    for (var y = y0; y < y1; y = y + 1u) {
        for (var x = x0; x < x1; x = x + 1u) {
            // Past the room (lists sized ahead of the count) a pair is dropped whole: a listed
            // pair's slot is always within the room, where the backward pass writes by slot.
            if (at < pc.limit && slot < pc.limit) {
                tile_keys[at] = y * pc.tiles_x + x;
                pair_slots[at] = slot;
            }
            if (slot < pc.limit) {
                slot_gaussians[slot] = g;
            }
            at = at + 1u;
            slot = slot + 1u;
        }
    }
}

@compute @workgroup_size(256)
fn ranges_of_tiles(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32) {
    let i = linear_id(wid, nwg, lid);
    if (i >= pc.n) {
        return;
    }
    // Entries past the pairs (lists sized ahead) hold a key past every tile and sort last.
    let tile = sorted_tiles[i];
    if (tile >= pc.limit) {
        return;
    }
    ids[i] = slot_gaussians[min(sorted_slots[i], pc.n - 1u)];
    if (i == 0u || sorted_tiles[i - 1u] != tile) {
        ranges[2u * tile] = i;
    }
    if (i + 1u == pc.n || sorted_tiles[i + 1u] != tile) {
        ranges[2u * tile + 1u] = i + 1u;
    }
}
