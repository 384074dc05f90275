// Tile lists of the rasteriser (host side: engine/src/ops/raster/).
//
// `emit`: one invocation per Gaussian writes one (key, Gaussian index) pair per tile of its
// rectangle, from its place in the exclusive scan of the tile counts. The key holds the tile
// index in its high bits and the depth in its low `depth_bits`: the top bits of the depth's f32
// pattern, which orders like the depth itself since depths are positive. One radix sort of the
// keys then groups the pairs by tile, front to back within a tile, equal keys in Gaussian order.
// `ranges`: one invocation per sorted pair marks where each tile's run starts and ends.

struct Params {
    n: u32,          // Gaussians (emit) or pairs (ranges)
    tiles_x: u32,
    depth_bits: u32, // 32 - tile bits
    // emit: pairs the key buffers hold (writes past it are dropped, never out of bounds);
    // ranges: the number of tiles (keys of other tiles are ignored).
    limit: u32,
}

@group(0) @binding(0) var<storage, read> counts: array<u32>;
@group(0) @binding(1) var<storage, read> offsets: array<u32>;
@group(0) @binding(2) var<storage, read> rects: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> proj: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> keys: array<u32>;
@group(0) @binding(5) var<storage, read_write> values: array<u32>;
@group(0) @binding(6) var<storage, read> sorted_keys: array<u32>;
// Per tile: first pair and one past the last.
@group(0) @binding(7) var<storage, read_write> ranges: array<u32>;
var<immediate> pc: Params;

@compute @workgroup_size(256)
fn emit(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let g = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (g >= pc.n || counts[g] == 0u) {
        return;
    }
    let r = rects[g];
    let x0 = r.x & 0xffffu;
    let y0 = r.x >> 16u;
    let x1 = r.y & 0xffffu;
    let y1 = r.y >> 16u;
    let depth = bitcast<u32>(proj[3u * g].z) >> (32u - pc.depth_bits);
    var at = offsets[g];
    for (var y = y0; y < y1; y = y + 1u) {
        for (var x = x0; x < x1; x = x + 1u) {
            if (at < pc.limit) {
                keys[at] = ((y * pc.tiles_x + x) << pc.depth_bits) | depth;
                values[at] = g;
            }
            at = at + 1u;
        }
    }
}

@compute @workgroup_size(256)
fn ranges_of_tiles(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32) {
    let i = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (i >= pc.n) {
        return;
    }
    let tile = sorted_keys[i] >> pc.depth_bits;
    if (tile >= pc.limit) {
        return;
    }
    if (i == 0u || (sorted_keys[i - 1u] >> pc.depth_bits) != tile) {
        ranges[2u * tile] = i;
    }
    if (i + 1u == pc.n || (sorted_keys[i + 1u] >> pc.depth_bits) != tile) {
        ranges[2u * tile + 1u] = i + 1u;
    }
}
