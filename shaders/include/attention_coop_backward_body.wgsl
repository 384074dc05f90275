// Fused segment attention, backward, on f16 q, k and v with cooperative matrices: the same
// operation, work lists, bindings and outputs as `bwd_dq` and `bwd_dkv` in attention_f16.wgsl
// (dO, o, lse in f32; delta, dq, dk, dv out in f32), with every product on FxFxF f16
// fragments accumulated in f32, in FlashAttention-2's structure: the scores and weights of
// each block are recomputed from the forward pass's row log-sum-exp, never stored.
//
// Two front files set the fragment size (see attention_coop_common.wgsl for what they define):
//   attention_coop_bwd.wgsl   F = 16, subgroups of 32 (NVIDIA);
//   attention_coop8_bwd.wgsl  F = 8, subgroups of 8 (lavapipe from Mesa 26).
// Both own BQ = 32 rows per workgroup (one subgroup per F of them) and stage the other side in
// tiles of BK = 32 rows, double-buffered as in the forward pass.
//
// `dq`: one workgroup per block of query rows. Each subgroup keeps its rows' Q and dO as
// fragments (dO rounded to f16 as it is staged, as the f16 products of the linear layers round
// their gradients) and its rows' dQ accumulator, and first computes its rows'
// delta = rowsum(dO * O) in f32 from that f16 dO and the f32 o (written out for `dkv`). For
// each tile of keys:
// 1. S = Q K^T and dP = dO V^T, stored row-major as f32 (barrier 1);
// 2. row-wise, in f32: P = exp(S*scale - lse), dS = P (dP - delta), stored as f16 (zero for
//    keys past the tile's end); the next tile is staged meanwhile (barrier 2);
// 3. dQ += dS K.
// At the end dQ * scale goes out through workgroup memory.
//
// `dkv`: one workgroup per block of key rows. Each subgroup keeps its keys' K and V as
// fragments and its keys' dK and dV accumulators. For each tile of queries (with their lse
// and delta staged beside them):
// 1. S^T = K Q^T and dP^T = V dO^T (barrier 1);
// 2. key-wise: P^T = exp(S^T*scale - lse), dS^T = P^T (dP^T - delta), both stored as f16
//    (zero for queries past the tile's end); the next tile is staged meanwhile (barrier 2);
// 3. dV += P^T dO and dK += dS^T Q.
// At the end dK * scale and dV go out. Every sum runs in a fixed order and nothing is
// accumulated by atomics: the same inputs give the same bits.

// @include attention_common.wgsl
// @include attention_coop_common.wgsl

@group(0) @binding(6) var<storage, read> o: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> lse: array<f32>;
@group(0) @binding(8) var<storage, read> d_o: array<vec4<f32>>;
@group(0) @binding(9) var<storage, read_write> delta: array<f32>;
@group(0) @binding(10) var<storage, read_write> dq: array<f32>;
@group(0) @binding(11) var<storage, read_write> dk: array<f32>;
@group(0) @binding(12) var<storage, read_write> dv: array<f32>;

// Both owned tensors (Q and dO, or K and V) are staged through kv at once.
const_assert BQ <= 2u * BK;

// Each subgroup's F rows of f32 dP (or dP^T), beside S in `so`.
var<workgroup> sd: array<f32, NSG * F * RS>;
// dk/dv: each subgroup's F rows of f16 dS^T, beside P^T in `ps`; and each staged tile's lse
// and delta (per half of the double buffer: lse, delta).
var<workgroup> pd: array<f16, NSG * F * RP>;
var<workgroup> stats: array<f32, 4u * BK>;

// Element `src` (4 features) of tensor `which` (0 q, 1 k, 2 v, 3 dO rounded to f16).
fn load_rows(which: u32, src: u32) -> vec4<f16> {
    if which == 0u {
        return unpack4(q[src]);
    } else if which == 1u {
        return unpack4(k[src]);
    } else if which == 2u {
        return unpack4(v[src]);
    }
    return d_o_half(src);
}

// Element `src` of dO, rounded to f16: what the products see, and what delta is made of.
fn d_o_half(src: u32) -> vec4<f16> {
    let g = d_o[src];
    return vec4<f16>(half(g.x), half(g.y), half(g.z), half(g.w));
}

fn pos_inf() -> f32 {
    return bitcast<f32>(0x7f800000u);
}

// The work item of this workgroup (see attention_common.wgsl), without the early return of
// the portable kernels: naga takes any return before a cooperative operation as making control
// flow non-uniform. An unused list entry gets no rows and an empty other side instead, and
// runs straight to the end. Returns (first owned row, owned rows, other side's begin and end);
// the owned side is the keys' where `keys_own`.
fn coop_item(wid: vec3<u32>, nwg: vec3<u32>, keys_own: bool) -> vec4<u32> {
    let id = wid.x + wid.y * nwg.x;
    let w = work[min(id, pc.items - 1u) / pc.heads];
    let valid = id < pc.items && w.x != 0xffffffffu;
    let rows = segment_rows(select(0u, w.x, valid), keys_own);
    let nrows = select(0u, min(BQ, rows.x - w.y), valid && rows.x > w.y);
    return vec4<u32>(w.y, nrows, rows.y, select(rows.y, rows.z, valid));
}

// f32 to f16, with magnitudes that round past the largest half (65504) made infinities of
// their sign, as IEEE rounding gives (what a plain conversion does there is left to the
// device): an overflow in a scaled-loss f16 step must reach the gradient norm as Inf or NaN,
// which makes the trainer lower the loss scale.
fn half(x: f32) -> f16 {
    return f16(select(x, x * pos_inf(), abs(x) >= 65520.0));
}

// The subgroup's two score products against the staged tile pair at x_at, y_at: S = A X^T
// into its rows of `so` and dP = B Y^T into its rows of `sd`, f32, row-major (A, B its own
// fragments: Q and dO in dq, K and V in dk/dv; X, Y the tile's K and V, or Q and dO). X^T's
// and Y^T's fragments (k = feature, n = tile row) are X and Y read column-major. naga 30 lowers
// coopStore without first emitting the expressions in its arguments, so each argument is
// bound by an earlier `let`.
fn scores(a: ptr<function, array<FragA, DF>>, b: ptr<function, array<FragA, DF>>,
          x_at: u32, y_at: u32, s_at: u32) {
    var zero: FragC;
    for (var c = 0u; c < KF; c++) {
        var s = zero;
        var dp = zero;
        for (var d = 0u; d < DF; d++) {
            let bx = coopLoad<FragB>(&kv[(x_at + c * F * RQ + d * F) / 4u], RQ / 4u);
            s = coopMultiplyAdd((*a)[d], bx, s);
            let by = coopLoad<FragB>(&kv[(y_at + c * F * RQ + d * F) / 4u], RQ / 4u);
            dp = coopMultiplyAdd((*b)[d], by, dp);
        }
        let sv = s;
        let s_dst = &so[s_at + c * F];
        let dpv = dp;
        let dp_dst = &sd[s_at + c * F];
        let stride = RS;
        coopStoreT(sv, s_dst, stride);
        coopStoreT(dpv, dp_dst, stride);
    }
}

@compute @workgroup_size(WG)
fn dq_coop(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) t: u32, @builtin(subgroup_id) sg: u32,
           @builtin(subgroup_invocation_id) lane: u32) {
    let item = coop_item(wid, nwg, false);
    let q0 = item.x;
    let nrows = item.y;
    let k_begin = item.z;
    let k_end = item.w;
    let h = (wid.x + wid.y * nwg.x) % pc.heads;
    // This subgroup's first row in the block; this lane's row among them (r) and its place
    // among the row's LPR lanes (j); the subgroup's scores and weights in workgroup memory.
    let row0 = sg * F;
    let r = lane / LPR;
    let j = lane % LPR;
    let s_at = sg * F * RS;
    let p_at = sg * F * RP;
    let mine = row0 + r < nrows;
    let row = q0 + row0 + r;
    var zero: FragC;

    // The row's statistics: lse from the forward pass (+inf for rows past the block, whose
    // weights are then zero) and delta = dO . o in f32, its features split over the row's
    // lanes. delta takes dO rounded to f16, as dP = dO V^T does: where the softmax is one-hot,
    // o is the chosen value row and dP - delta must vanish, which it does only if both are
    // made of the same dO (with the f32 dO, dq picks up dO's rounding times the key).
    var row_lse = pos_inf();
    var row_delta = 0.0;
    if mine {
        row_lse = lse[row * pc.heads + h];
        for (var c = j; c < D4; c += LPR) {
            let at = (row * pc.heads + h) * D4 + c;
            row_delta += dot(vec4<f32>(d_o_half(at)), o[at]);
        }
    }
    for (var x = 1u; x < LPR; x <<= 1u) {
        row_delta += subgroupShuffleXor(row_delta, x);
    }
    if mine && j == 0u {
        // dkv reads delta after this kernel (the recorder puts a barrier between them).
        delta[row * pc.heads + h] = row_delta;
    }

    // Q and dO, staged once through kv and kept as fragments.
    stage(0u, q0, nrows, h, 0u, BQ, t);
    stage(3u, q0, nrows, h, BQ * RQ, BQ, t);
    workgroupBarrier();
    var qf: array<FragA, DF>;
    var gf: array<FragA, DF>;
    var acc: array<FragC, DF>;
    for (var d = 0u; d < DF; d++) {
        qf[d] = coopLoadT<FragA>(&kv[(row0 * RQ + d * F) / 4u], RQ / 4u);
        gf[d] = coopLoadT<FragA>(&kv[((BQ + row0) * RQ + d * F) / 4u], RQ / 4u);
        acc[d] = zero;
    }
    // Every fragment is loaded before the first tile overwrites kv.
    workgroupBarrier();
    if k_begin < k_end {
        stage_pair(1u, 2u, k_begin, k_end, h, 0u, t);
    }
    workgroupBarrier();

    for (var kt = k_begin; kt < k_end; kt += BK) {
        let parity = ((kt - k_begin) / BK) & 1u;
        let count = min(BK, k_end - kt);
        let k_at = parity * 2u * KV_TILE;
        let v_at = k_at + KV_TILE;

        // 1. S = Q K^T and dP = dO V^T.
        scores(&qf, &gf, k_at, v_at, s_at);
        workgroupBarrier();

        // 2. dS = P (dP - delta), row-wise in f32, rounded to f16 for the product.
        for (var i = 0u; i < KPL; i++) {
            let key = j + LPR * i;
            let at = s_at + r * RS + key;
            let p = exp(so[at] * pc.scale - row_lse);
            ps[p_at + r * RP + key] = half(select(0.0, p * (sd[at] - row_delta), key < count));
        }
        // The next tile goes to the other half of kv, last read by the previous tile's dS K,
        // before barrier 1.
        if kt + BK < k_end {
            stage_pair(1u, 2u, kt + BK, k_end, h, parity ^ 1u, t);
        }
        workgroupBarrier();

        // 3. dQ += dS K: K's fragment (k = key, n = feature) is K read row-major.
        var sf: array<FragA, KF>;
        for (var c = 0u; c < KF; c++) {
            sf[c] = coopLoadT<FragA>(&ps[p_at + c * F], RP);
        }
        for (var d = 0u; d < DF; d++) {
            for (var c = 0u; c < KF; c++) {
                let b = coopLoadT<FragB>(&kv[(k_at + c * F * RQ + d * F) / 4u], RQ / 4u);
                acc[d] = coopMultiplyAdd(sf[c], b, acc[d]);
            }
        }
    }
    for (var d0 = 0u; d0 < DF; d0 += KF) {
        spill(&acc, d0, s_at);
        for (var c = j; c < KF * F; c += LPR) {
            let feature = d0 * F + c;
            if mine && feature < D {
                dq[(row * pc.heads + h) * D + feature] = so[s_at + r * RS + c] * pc.scale;
            }
        }
    }
}

@compute @workgroup_size(WG)
fn dkv_coop(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) t: u32, @builtin(subgroup_id) sg: u32,
            @builtin(subgroup_invocation_id) lane: u32) {
    // Work items here are blocks of keys.
    let item = coop_item(wid, nwg, true);
    let k0 = item.x;
    let nrows = item.y;
    let q_begin = item.z;
    let q_end = item.w;
    let h = (wid.x + wid.y * nwg.x) % pc.heads;
    let row0 = sg * F;
    let r = lane / LPR;
    let j = lane % LPR;
    let s_at = sg * F * RS;
    let p_at = sg * F * RP;
    var zero: FragC;

    // K and V, staged once through kv and kept as fragments.
    stage(1u, k0, nrows, h, 0u, BQ, t);
    stage(2u, k0, nrows, h, BQ * RQ, BQ, t);
    workgroupBarrier();
    var kf: array<FragA, DF>;
    var vf: array<FragA, DF>;
    var gk: array<FragC, DF>;
    var gv: array<FragC, DF>;
    for (var d = 0u; d < DF; d++) {
        kf[d] = coopLoadT<FragA>(&kv[(row0 * RQ + d * F) / 4u], RQ / 4u);
        vf[d] = coopLoadT<FragA>(&kv[((BQ + row0) * RQ + d * F) / 4u], RQ / 4u);
        gk[d] = zero;
        gv[d] = zero;
    }
    workgroupBarrier();
    if q_begin < q_end {
        stage_queries(q_begin, q_end, h, 0u, t);
    }
    workgroupBarrier();

    for (var qt = q_begin; qt < q_end; qt += BK) {
        let parity = ((qt - q_begin) / BK) & 1u;
        let count = min(BK, q_end - qt);
        let q_at = parity * 2u * KV_TILE;
        let g_at = q_at + KV_TILE;
        let st = parity * 2u * BK;

        // 1. S^T = K Q^T and dP^T = V dO^T.
        scores(&kf, &vf, q_at, g_at, s_at);
        workgroupBarrier();

        // 2. P^T and dS^T = P^T (dP^T - delta), key-wise in f32, both rounded to f16.
        for (var i = 0u; i < KPL; i++) {
            let query = j + LPR * i;
            let at = s_at + r * RS + query;
            let live = query < count;
            let p = select(0.0, exp(so[at] * pc.scale - stats[st + query]), live);
            ps[p_at + r * RP + query] = f16(p);
            pd[p_at + r * RP + query] = half(p * (sd[at] - stats[st + BK + query]));
        }
        if qt + BK < q_end {
            stage_queries(qt + BK, q_end, h, parity ^ 1u, t);
        }
        workgroupBarrier();

        // 3. dV += P^T dO and dK += dS^T Q: dO's and Q's fragments (k = query, n = feature)
        // are read row-major.
        var pf: array<FragA, KF>;
        var sf: array<FragA, KF>;
        for (var c = 0u; c < KF; c++) {
            pf[c] = coopLoadT<FragA>(&ps[p_at + c * F], RP);
            sf[c] = coopLoadT<FragA>(&pd[p_at + c * F], RP);
        }
        for (var d = 0u; d < DF; d++) {
            for (var c = 0u; c < KF; c++) {
                let bg = coopLoadT<FragB>(&kv[(g_at + c * F * RQ + d * F) / 4u], RQ / 4u);
                gv[d] = coopMultiplyAdd(pf[c], bg, gv[d]);
                let bq = coopLoadT<FragB>(&kv[(q_at + c * F * RQ + d * F) / 4u], RQ / 4u);
                gk[d] = coopMultiplyAdd(sf[c], bq, gk[d]);
            }
        }
    }
    let mine = row0 + r < nrows;
    let row = k0 + row0 + r;
    for (var d0 = 0u; d0 < DF; d0 += KF) {
        spill(&gk, d0, s_at);
        for (var c = j; c < KF * F; c += LPR) {
            let feature = d0 * F + c;
            if mine && feature < D {
                dk[(row * pc.heads + h) * D + feature] = so[s_at + r * RS + c] * pc.scale;
            }
        }
        spill(&gv, d0, s_at);
        for (var c = j; c < KF * F; c += LPR) {
            let feature = d0 * F + c;
            if mine && feature < D {
                dv[(row * pc.heads + h) * D + feature] = so[s_at + r * RS + c];
            }
        }
    }
}

// Stages the queries and output gradients of the tile starting at query `first` into half
// `half` of kv, and their lse and delta into the same half of `stats` (zero past the segment:
// those queries are masked).
fn stage_queries(first: u32, end: u32, h: u32, half: u32, t: u32) {
    stage_pair(0u, 3u, first, end, h, half, t);
    let count = min(BK, end - first);
    for (var i = t; i < BK; i += WG) {
        var l = 0.0;
        var dl = 0.0;
        if i < count {
            l = lse[(first + i) * pc.heads + h];
            dl = delta[(first + i) * pc.heads + h];
        }
        stats[half * 2u * BK + i] = l;
        stats[half * 2u * BK + BK + i] = dl;
    }
}
