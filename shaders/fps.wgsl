// Farthest point sampling in 4D over m candidates, down to k. Host side: engine/src/ops/fps.rs.
//
// One workgroup of WG invocations runs every iteration inside one dispatch, so no global
// synchronisation is needed. Invocation `lid` owns candidates lid, lid + WG, lid + 2 WG, ...
// and keeps their squared distance to the chosen set in `min_dist` (only it reads and writes
// those entries). Candidate 0 is chosen first. Each iteration measures the owned candidates
// against the newest chosen one, lowers their distances, and marks the newest chosen -1 so
// that it is never picked again (every distance is >= 0, so duplicates of a chosen point can
// still be picked, in index order); then an argmax over the workgroup, a 4-way tree in
// workgroup memory (half the barriers of a 2-way one, which made it 1.3x faster on lavapipe),
// picks the next candidate: the largest distance, ties to the lower candidate index. The tree
// uses workgroup memory only, never subgroup operations, so it does not depend on the
// subgroup size (8 on lavapipe, 32 on NVIDIA, 64 on AMD).

struct Params {
    m: u32, // candidates
    k: u32, // to choose, 1..=m
}

const WG: u32 = 1024u;

@group(0) @binding(0) var<storage, read> cands: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> cand_index: array<u32>;
@group(0) @binding(2) var<storage, read_write> min_dist: array<f32>;
@group(0) @binding(3) var<storage, read_write> chosen: array<u32>;
var<immediate> pc: Params;

var<workgroup> best_dist: array<f32, WG>;
var<workgroup> best_index: array<u32, WG>;

@compute @workgroup_size(1024)
fn main(@builtin(local_invocation_index) lid: u32) {
    if (pc.k == 0u) {
        return;
    }
    var current = 0u;
    if (lid == 0u) {
        chosen[0] = cand_index[0];
    }
    for (var it = 1u; it < pc.k; it++) {
        let c = cands[current];
        // Below every stored distance (>= -1), so an invocation without candidates never wins.
        var bd = -2.0;
        var bi = 0u;
        // Increasing j and a strict comparison: ties go to the lower index.
        for (var j = lid; j < pc.m; j += WG) {
            let diff = cands[j] - c;
            var md = dot(diff, diff);
            if (it > 1u) {
                md = min(min_dist[j], md);
            }
            if (j == current) {
                md = -1.0;
            }
            min_dist[j] = md;
            if (md > bd) {
                bd = md;
                bi = j;
            }
        }
        best_dist[lid] = bd;
        best_index[lid] = bi;
        workgroupBarrier();
        // 1024 -> 256 -> 64 -> 16 -> 4 -> 1: five barriers.
        for (var s = WG / 4u; s > 0u; s >>= 2u) {
            if (lid < s) {
                var md = best_dist[lid];
                var mi = best_index[lid];
                for (var r = 1u; r < 4u; r++) {
                    let od = best_dist[lid + r * s];
                    let oi = best_index[lid + r * s];
                    if (od > md || (od == md && oi < mi)) {
                        md = od;
                        mi = oi;
                    }
                }
                best_dist[lid] = md;
                best_index[lid] = mi;
            }
            workgroupBarrier();
        }
        current = best_index[0];
        if (lid == 0u) {
            chosen[it] = cand_index[current];
        }
        // Everyone has read the winner before the next iteration overwrites the tree.
        workgroupBarrier();
    }
}
