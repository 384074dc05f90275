// Fused segment attention, forward, on f16 q, k and v with cooperative matrices: the same
// operation, work list, bindings and outputs as `fwd` in attention_f16.wgsl (o and lse f32),
// with both products, S = Q K^T and P V, on FxFxF f16 fragments accumulated in f32.
//
// Two front files set the fragment size and the shapes that follow from it, then include this
// body (each compiled once per head width D and block height BQ):
//   attention_coop.wgsl   F = 16, subgroups of 32 (NVIDIA), BQ = 32 or 128 query rows;
//   attention_coop8.wgsl  F = 8, subgroups of 8 (lavapipe from Mesa 26), BQ = 32 or 64;
// both with tiles of BK = 32 or 64 keys (fewer barriers per key for long segments, where the
// workgroup memory holds them). Each defines FragA, FragB, FragC, F, BK, BQ, D, and PAD_H,
// PAD_F (row padding of the f16 and f32 tiles, in elements, which spreads rows over the
// banks).
//
// One workgroup takes one work item: BQ query rows of one segment and one head. It has one
// subgroup per F query rows, and each subgroup owns its rows from start to end, as in
// FlashAttention-2: it keeps their Q fragments and their running, unnormalised output O in
// registers, and their scores S and weights P in its own corner of workgroup memory. What the
// subgroups share is the staged tile of keys and values, so a taller block (BQ = 128 for long
// segments) reads each key and value from device memory once per 128 query rows instead of
// once per 32, and stages it once for 8 subgroups. For each tile of BK keys:
// 1. S = Q K^T, BK/F fragments per subgroup, stored row-major as f32 (barrier 1);
// 2. the online softmax of the subgroup's rows, in f32: each row belongs to LPR = SG/F lanes
//    (2 on NVIDIA, 1 on lavapipe), which take the tile's maximum with xor shuffles. The running
//    maximum m moves lazily: only when some row's tile maximum exceeds its m by more than
//    RESCALE_MARGIN, and then for every row of the block at once (a workgroup vote read by
//    workgroupUniformLoad, barrier 2, so that the decision is uniform: WGSL cooperative
//    matrices must be used in uniform control flow). Moving it rescales the output fragments,
//    through workgroup memory since WGSL cooperative matrices give no element access; the
//    first tile, whose output is still zero, never needs to. P = exp(S*scale - m) (below e^8)
//    goes to workgroup memory as f16, and the running sum adds the rounded P, so the weights
//    that multiply V are exactly the ones the output is divided by (barrier 3);
// 3. O += P V on the subgroup's output fragments.
// Meanwhile the next tile's keys and values are staged into the other half of a double buffer
// (between barriers 1 and 2; both halves are free then), so a tile costs three barriers.
// After the last tile the output fragments go through workgroup memory; each row's lanes
// divide by the row's sum (their partial sums, added by shuffles) and write their features;
// lane 0 of the row writes the log-sum-exp. A segment with no keys gets zeros and lse = -inf,
// as in the portable kernels.

// @include attention_common.wgsl
// @include attention_coop_common.wgsl

@group(0) @binding(6) var<storage, read_write> o: array<f32>;
@group(0) @binding(7) var<storage, read_write> lse: array<f32>;

// The queries are staged through kv, four tiles' worth.
const_assert BQ <= 4u * BK;

// Per tile parity: bit 0, some row wants to move the running maxima; bit 1, first tile.
var<workgroup> vote: array<atomic<u32>, 2>;

// How far a score may exceed the running maximum before the maxima move: P stays below
// e^8 (about 3000), far inside f16's range, with f16's relative precision.
const RESCALE_MARGIN: f32 = 8.0;

// Element `src` (4 features) of tensor `which` (0 q, 1 k, 2 v), for `chunk`.
fn load_rows(which: u32, src: u32) -> vec4<f16> {
    if which == 0u {
        return unpack4(q[src]);
    } else if which == 1u {
        return unpack4(k[src]);
    }
    return unpack4(v[src]);
}

@compute @workgroup_size(WG)
fn fwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
       @builtin(local_invocation_index) t: u32, @builtin(subgroup_id) sg: u32,
       @builtin(subgroup_invocation_id) lane: u32) {
    // The work item, without the early return of the portable kernels: naga takes any return
    // before a cooperative operation as making control flow non-uniform. An unused list entry
    // gets no rows and no keys instead, and runs straight to the end.
    let id = wid.x + wid.y * nwg.x;
    let w = work[min(id, pc.items - 1u) / pc.heads];
    let valid = id < pc.items && w.x != 0xffffffffu;
    let seg = select(0u, w.x, valid);
    let h = id % pc.heads;
    let q0 = w.y;
    let q_end = min(q_off[seg + 1u], pc.nq);
    let nrows = select(0u, min(BQ, q_end - q0), valid && q_end > q0);
    let k_begin = min(k_off[seg], pc.nk);
    let k_end = select(k_begin, clamp(k_off[seg + 1u], k_begin, pc.nk), valid);
    // This subgroup's first row in the block; this lane's row among them (r) and its place
    // among the row's LPR lanes (j); the subgroup's S and P in workgroup memory.
    let row0 = sg * F;
    let r = lane / LPR;
    let j = lane % LPR;
    let s_at = sg * F * RS;
    let p_at = sg * F * RP;

    // A zero fragment to start each product from (a variable declared without initialiser is
    // zero; copying it makes that explicit).
    var zero: FragC;
    var m = neg_inf();
    var l = 0.0;

    // The queries, staged once through kv and kept as fragments.
    stage(0u, q0, nrows, h, 0u, BQ, t);
    // Workgroup memory starts undefined: clear the votes before the first tile.
    if t == 0u {
        atomicStore(&vote[0], 0u);
        atomicStore(&vote[1], 0u);
    }
    workgroupBarrier();
    var qf: array<FragA, DF>;
    for (var d = 0u; d < DF; d++) {
        qf[d] = coopLoadT<FragA>(&kv[(row0 * RQ + d * F) / 4u], RQ / 4u);
    }
    var oacc: array<FragC, DF>;
    for (var d = 0u; d < DF; d++) {
        oacc[d] = zero;
    }
    // Every Q fragment is loaded before the first tile overwrites kv.
    workgroupBarrier();
    if k_begin < k_end {
        stage_pair(1u, 2u, k_begin, k_end, h, 0u, t);
    }
    workgroupBarrier();

    for (var kt = k_begin; kt < k_end; kt += BK) {
        let tile = (kt - k_begin) / BK;
        let count = min(BK, k_end - kt);
        let k_at = (tile & 1u) * 2u * KV_TILE;
        let v_at = k_at + KV_TILE;

        // 1. S = Q K^T. K^T's fragment (k = feature, n = key) is K read column-major. naga 30
        // lowers coopStore without first emitting the expressions in its arguments, so each
        // argument is bound by an earlier `let`.
        for (var c = 0u; c < KF; c++) {
            var s = zero;
            for (var d = 0u; d < DF; d++) {
                let b = coopLoad<FragB>(&kv[(k_at + c * F * RQ + d * F) / 4u], RQ / 4u);
                s = coopMultiplyAdd(qf[d], b, s);
            }
            let value = s;
            let dst = &so[s_at + c * F];
            let stride = RS;
            coopStoreT(value, dst, stride);
        }
        workgroupBarrier();

        // 2. Online softmax of row r over this tile's keys, with a lazy maximum: the running
        // maximum m moves only when a score exceeds it by more than RESCALE_MARGIN, and then
        // for every row of the block at once.
        var sv: array<f32, KPL>;
        var tile_max = neg_inf();
        for (var i = 0u; i < KPL; i++) {
            let key = j + LPR * i;
            sv[i] = select(neg_inf(), so[s_at + r * RS + key] * pc.scale, key < count);
            tile_max = max(tile_max, sv[i]);
        }
        for (var x = 1u; x < LPR; x <<= 1u) {
            tile_max = max(tile_max, subgroupShuffleXor(tile_max, x));
        }
        // Tiles alternate between two vote words: this tile's is raised by the subgroups that
        // want to move, read by all after a barrier (a uniform decision), and the other one,
        // last read a tile ago, is cleared for the next tile.
        let parity = tile & 1u;
        let wants = subgroupAny(tile_max > m + RESCALE_MARGIN);
        if lane == 0u && wants {
            atomicOr(&vote[parity], 1u);
        }
        if t == 0u {
            atomicStore(&vote[parity ^ 1u], 0u);
            if tile == 0u {
                atomicOr(&vote[parity], 2u);
            }
        }
        // The next tile's keys and values go to the other half of kv, last read by the previous
        // tile's P V, before barrier 1.
        if kt + BK < k_end {
            stage_pair(1u, 2u, kt + BK, k_end, h, parity ^ 1u, t);
        }
        let decided = workgroupUniformLoad(&vote[parity]);
        let rescale = (decided & 1u) != 0u;
        let m_new = select(m, max(m, tile_max), rescale);
        let correction = exp(m - m_new);
        l *= correction;
        for (var i = 0u; i < KPL; i++) {
            let p = f16(exp(sv[i] - m_new));
            ps[p_at + r * RP + j + LPR * i] = p;
            l += f32(p);
        }
        m = m_new;
        // Rescaling the output fragments goes through the subgroup's S, whose scores were all
        // read before barrier 2, KF fragments at a time. The first tile's output is zero and
        // needs none.
        if decided == 1u {
            for (var d0 = 0u; d0 < DF; d0 += KF) {
                store_round(&oacc, d0, s_at);
                workgroupBarrier();
                for (var c = j; c < KF * F; c += LPR) {
                    so[s_at + r * RS + c] *= correction;
                }
                workgroupBarrier();
                for (var x = 0u; x < KF; x++) {
                    oacc[min(d0 + x, DF - 1u)] = coopLoadT<FragC>(&so[s_at + x * F], RS);
                }
                workgroupBarrier();
            }
        }
        workgroupBarrier();

        // 3. O += P V. V's fragment (k = key, n = feature) is V read row-major.
        var pf: array<FragA, KF>;
        for (var c = 0u; c < KF; c++) {
            pf[c] = coopLoadT<FragA>(&ps[p_at + c * F], RP);
        }
        for (var d = 0u; d < DF; d++) {
            for (var c = 0u; c < KF; c++) {
                let b = coopLoadT<FragB>(&kv[(v_at + c * F * RQ + d * F) / 4u], RQ / 4u);
                oacc[d] = coopMultiplyAdd(pf[c], b, oacc[d]);
            }
        }
    }

    // The output, KF fragments at a time through the subgroup's S: each row's lanes divide by
    // the row's sum and write their features.
    for (var x = 1u; x < LPR; x <<= 1u) {
        l += subgroupShuffleXor(l, x);
    }
    var inv = 0.0;
    var row_lse = neg_inf();
    if l > 0.0 {
        inv = 1.0 / l;
        row_lse = m + log(l);
    }
    let mine = row0 + r < nrows;
    let row = q0 + row0 + r;
    for (var d0 = 0u; d0 < DF; d0 += KF) {
        spill(&oacc, d0, s_at);
        for (var c = j; c < KF * F; c += LPR) {
            let feature = d0 * F + c;
            if mine && feature < D {
                o[(row * pc.heads + h) * D + feature] = so[s_at + r * RS + c] * inv;
            }
        }
    }
    if mine && j == 0u {
        lse[row * pc.heads + h] = row_lse;
    }
}
