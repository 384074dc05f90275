// Nearest-query assignment in 4D, and the offsets of the per-query cells. Host side and
// format: engine/src/ops/assign.rs.
//
// `nearest`: brute force over all queries, tiled. A workgroup owns WG * PTS points (each
// invocation PTS of them, WG apart so that loads are coalesced) and walks the queries in tiles
// of TILE: the workgroup loads a tile into workgroup memory, then every invocation measures its
// points against each query of the tile (a broadcast read) and keeps, per point, the smallest
// squared distance and its query. Queries are visited in increasing index and only a strictly
// smaller distance replaces the best, so ties go to the lower index. Several points per
// invocation amortise each workgroup-memory read over PTS distance evaluations.
//
// `cell_offsets`: given the cell ids sorted ascending, offsets[c] = the number of points in
// cells below c, for every c in 0..=k. Invocation i in 0..=n writes offsets[c] = i for the c in
// (sorted[i - 1], sorted[i]] (with sorted[-1] = -1 and sorted[n] = k): these ranges partition
// 0..=k, so every entry is written once, empty cells included, without atomics. (Ids are
// clamped to k so that a bad id cannot write past the end.)

struct Params {
    n: u32, // points
    k: u32, // queries
}

const WG: u32 = 128u;
const PTS: u32 = 4u;
const TILE: u32 = 256u;

@group(0) @binding(0) var<storage, read> points: array<f32>;
@group(0) @binding(1) var<storage, read> queries: array<f32>;
@group(0) @binding(2) var<storage, read_write> cells: array<u32>;
@group(0) @binding(3) var<storage, read> sorted_cells: array<u32>;
@group(0) @binding(4) var<storage, read_write> offsets: array<u32>;
var<immediate> pc: Params;

var<workgroup> tile: array<vec4<f32>, TILE>;

fn load_point(i: u32) -> vec4<f32> {
    if (i >= pc.n) {
        return vec4<f32>(0.0);
    }
    return vec4<f32>(points[4u * i], points[4u * i + 1u], points[4u * i + 2u], points[4u * i + 3u]);
}

fn dist2(a: vec4<f32>, b: vec4<f32>) -> f32 {
    let d = a - b;
    return dot(d, d);
}

@compute @workgroup_size(128)
fn nearest(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let first = (wid.x + wid.y * nwg.x) * (WG * PTS) + lid;
    // Uniform across the workgroup (the workgroup's first point is past the end), so leaving
    // before the barriers is safe.
    if (first - lid >= pc.n) {
        return;
    }
    let p0 = load_point(first);
    let p1 = load_point(first + WG);
    let p2 = load_point(first + 2u * WG);
    let p3 = load_point(first + 3u * WG);
    let inf = bitcast<f32>(0x7f800000u);
    var b0 = inf;
    var b1 = inf;
    var b2 = inf;
    var b3 = inf;
    var i0 = 0u;
    var i1 = 0u;
    var i2 = 0u;
    var i3 = 0u;
    for (var t0 = 0u; t0 < pc.k; t0 += TILE) {
        let count = min(TILE, pc.k - t0);
        // Every invocation has finished with the previous tile.
        workgroupBarrier();
        for (var j = lid; j < count; j += WG) {
            let q = 4u * (t0 + j);
            tile[j] = vec4<f32>(queries[q], queries[q + 1u], queries[q + 2u], queries[q + 3u]);
        }
        workgroupBarrier();
        for (var j = 0u; j < count; j++) {
            let q = tile[j];
            let id = t0 + j;
            let d0 = dist2(p0, q);
            let d1 = dist2(p1, q);
            let d2 = dist2(p2, q);
            let d3 = dist2(p3, q);
            if (d0 < b0) { b0 = d0; i0 = id; }
            if (d1 < b1) { b1 = d1; i1 = id; }
            if (d2 < b2) { b2 = d2; i2 = id; }
            if (d3 < b3) { b3 = d3; i3 = id; }
        }
    }
    if (first < pc.n) { cells[first] = i0; }
    if (first + WG < pc.n) { cells[first + WG] = i1; }
    if (first + 2u * WG < pc.n) { cells[first + 2u * WG] = i2; }
    if (first + 3u * WG < pc.n) { cells[first + 3u * WG] = i3; }
}

@compute @workgroup_size(256)
fn cell_offsets(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                @builtin(local_invocation_index) lid: u32) {
    let i = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (i > pc.n) {
        return;
    }
    var lo = 0u;
    if (i > 0u) {
        lo = min(sorted_cells[i - 1u], pc.k) + 1u;
    }
    var hi = pc.k;
    if (i < pc.n) {
        hi = min(sorted_cells[i], pc.k);
    }
    for (var c = lo; c <= hi; c++) {
        offsets[c] = i;
    }
}
