// @variants WG: 256 1024
// Farthest point sampling in 4D over m candidates, down to k. Host side: engine/src/ops/fps.rs.
//
// First `shaders/fps_order.wgsl` gives every candidate a Morton code and the host sorts them by
// it, so that neighbours in the sorted order are neighbours in space; `perm` holds the original
// position of each sorted slot.
//
// `main` (one workgroup of WG invocations) runs every iteration inside one dispatch, so no
// global synchronisation is needed. Invocation `lid` owns a run of `per` consecutive sorted
// slots, a compact piece of space, and keeps in registers their bounding box and the largest
// of their squared distances to the chosen set (`bd`, at slot `bi`, original position `bp`);
// the distances themselves are in `min_dist`, which only the owner reads and writes. Each
// iteration brings a new chosen point c. Lowering a distance to |x - c|^2 only matters where
// that is below it; an invocation whose box is farther from c than its largest distance
// (`bd`) changes nothing, and skips its slots without reading them. Late in the sampling, when
// the chosen points are dense, most invocations skip (at 8192 of 32768 points on a moving
// sphere, 16 of 1024 measure their runs in an average iteration), so an iteration reads the
// few boxes near c instead of every candidate.
// The others measure their slots against c, lower their distances, mark c's slot -1 so that it
// is never picked again (every distance is >= 0, so duplicates of a chosen point can still be
// picked), and take their maximum again. Then an argmax over the workgroup picks the next
// candidate: the largest distance, ties to the lower original position, which is the rule of
// the unsorted order, so the choices do not depend on the sort. The argmax takes subgroup
// maxima and one barrier, and works for any subgroup size (8 on lavapipe, 32 on NVIDIA, 64 on
// AMD); the 4-way tree in workgroup memory it replaced took five.
//
// Two workgroup sizes (`@variants WG`): 1024 for GPUs, where an active invocation's run of
// slots is a chain of load latencies that more invocations keep short, and 256 for lavapipe,
// where every invocation costs time at every iteration (engine/src/ops/fps.rs, `variant`).
//
// The skip test is exact, not a heuristic: the box's distance is computed with the same
// rounded operations, and rounding is monotonic, so every slot's computed distance is at least
// the computed box distance up to a few ulps; SAFE covers those, and an invocation skips only
// when the box distance exceeds `bd` by more than that. The choices equal the unskipped
// algorithm's bit for bit (engine/tests/ops/assign.rs compares them with the reference).

struct Params {
    m: u32, // candidates
    k: u32, // to choose, 1..=m
}

const WG: u32 = 1024u;
// The skip test's allowance for rounding: 1e-5 relative, about 170 ulps of f32.
const SAFE: f32 = 0.99999;
// Below this squared distance the relative argument would meet subnormals: never skip.
const TINY: f32 = 1e-30;
const BIG: f32 = 3.0e38;
const NONE: u32 = 0xffffffffu;

// The candidates in sorted order.
@group(0) @binding(0) var<storage, read> cands: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> perm: array<u32>;
@group(0) @binding(2) var<storage, read> cand_index: array<u32>;
@group(0) @binding(3) var<storage, read_write> min_dist: array<f32>;
@group(0) @binding(4) var<storage, read_write> chosen: array<u32>;
var<immediate> pc: Params;

// Each subgroup's winner, in two halves of WG entries (enough for subgroups of one).
var<workgroup> part_dist: array<f32, 2 * WG>;
var<workgroup> part_pos: array<u32, 2 * WG>;
var<workgroup> part_slot: array<u32, 2 * WG>;
var<workgroup> start_slot: u32;

@compute @workgroup_size(WG)
fn main(@builtin(local_invocation_index) lid: u32, @builtin(subgroup_id) sg: u32,
        @builtin(num_subgroups) nsg: u32, @builtin(subgroup_invocation_id) lane: u32) {
    // The subgroup's lanes, counted rather than read from the `subgroup_size` builtin: lavapipe
    // (Mesa 25.0) at LP_NATIVE_VECTOR_WIDTH=1024 reports 32 there but runs subgroups of 16,
    // and a step of 32 below would leave half the subgroups' winners unread
    // (engine/tests/ops/subgroups.rs measures both).
    let lanes = subgroupAdd(1u);
    let per = (pc.m + WG - 1u) / WG;
    let first = min(lid * per, pc.m);
    let end = min(first + per, pc.m);
    let owns = first < end;
    var lo = vec4<f32>(BIG);
    var hi = vec4<f32>(-BIG);
    for (var j = first; j < end; j++) {
        let p = cands[j];
        lo = min(lo, p);
        hi = max(hi, p);
        // FPS starts from the candidate at original position 0.
        if (perm[j] == 0u) {
            start_slot = j;
        }
    }
    if (lid == 0u) {
        chosen[0] = cand_index[0];
    }
    workgroupBarrier();
    var current = start_slot;
    // Below every stored distance (>= -1), so an invocation without slots never wins.
    var bd = -2.0;
    var bi = 0u;
    var bp = NONE;
    for (var it = 1u; it < pc.k; it++) {
        let c = cands[current];
        let gap = max(max(lo - c, c - hi), vec4<f32>(0.0));
        let bound = dot(gap, gap);
        // The invocation that holds c never skips (its box contains c: bound 0), so c's slot
        // is always marked.
        let skip = bound > TINY && bound * SAFE > bd;
        if (owns && (it == 1u || !skip)) {
            bd = -2.0;
            bp = NONE;
            for (var j0 = first; j0 < end; j0 += 4u) {
                // Four slots' loads are issued together: an active invocation's time on a GPU
                // is the latency of its loads, which a chain of one at a time would pay per slot.
                var xs: array<vec4<f32>, 4>;
                var old: array<f32, 4>;
                for (var u = 0u; u < 4u; u++) {
                    let j = min(j0 + u, end - 1u);
                    xs[u] = cands[j];
                    old[u] = min_dist[j];
                }
                for (var u = 0u; u < 4u; u++) {
                    let j = j0 + u;
                    if (j < end) {
                        let diff = xs[u] - c;
                        var md = dot(diff, diff);
                        if (it > 1u) {
                            md = min(old[u], md);
                        }
                        if (j == current) {
                            md = -1.0;
                        }
                        min_dist[j] = md;
                        // The original position breaks ties; it is read only for a new best.
                        if (md >= bd) {
                            let p = perm[j];
                            if (md > bd || p < bp) {
                                bd = md;
                                bi = j;
                                bp = p;
                            }
                        }
                    }
                }
            }
        }
        // The argmax: each subgroup's winner (largest distance, then lowest original
        // position; those pairs are distinct), then the winner of those, which every subgroup
        // finds for itself from the same entries. The entries alternate between two halves by
        // iteration, so the one barrier suffices: an iteration writes the half that was last read
        // before the previous iteration's barrier.
        let half = (it & 1u) * WG;
        let w = argmax(bd, bp, bi);
        if (lane == 0u) {
            part_dist[half + sg] = w.d;
            part_pos[half + sg] = w.p;
            part_slot[half + sg] = w.s;
        }
        workgroupBarrier();
        var e = Best(-3.0, NONE, 0u);
        for (var i = lane; i < nsg; i += lanes) {
            let o = Best(part_dist[half + i], part_pos[half + i], part_slot[half + i]);
            if (o.d > e.d || (o.d == e.d && o.p < e.p)) {
                e = o;
            }
        }
        let win = argmax(e.d, e.p, e.s);
        current = win.s;
        if (lid == 0u) {
            chosen[it] = cand_index[win.p];
        }
    }
}

struct Best {
    d: f32, // squared distance
    p: u32, // original position
    s: u32, // sorted slot
}

// The subgroup's largest d, ties to the lowest p, with its s.
fn argmax(d: f32, p: u32, s: u32) -> Best {
    let md = subgroupMax(d);
    let mp = subgroupMin(select(NONE, p, d == md));
    let ms = subgroupMin(select(NONE, s, d == md && p == mp));
    return Best(md, mp, ms);
}
