// Fused segment attention, forward, on f16 q, k and v with cooperative matrices: the same
// operation, work list, bindings and outputs as `fwd` in attention_f16.wgsl (o and lse f32),
// with both products, S = Q K^T and P V, on FxFxF f16 fragments accumulated in f32.
//
// Two front files set the fragment size and the shapes that follow from it, then include this
// body (each compiled once per head width D):
//   attention_coop.wgsl   F = 16, subgroups of 32 (NVIDIA), BK = 64 keys per tile;
//   attention_coop8.wgsl  F = 8, subgroups of 8 (lavapipe from Mesa 26), BK = 32.
// Each defines FragA, FragB, FragC, F, BK, D, and PAD_H, PAD_F (row padding of the f16 and f32
// tiles, in elements, which spreads rows over the banks where that matters).
//
// One workgroup of 256 invocations takes one work item: BQ = 32 query rows of one segment and
// one head. For each tile of BK keys of the segment:
// 1. the keys and values are staged into workgroup memory as f16 (rows past the segment and
//    features past D zero; the queries were staged once, the same way, before the loop);
// 2. S = Q K^T: (BQ/F) x (BK/F) fragments, each subgroup computing one (or, where there are
//    fewer fragments than subgroups, computing a copy it stores to a scratch slot: naga wants
//    every cooperative operation in uniform control flow, so no subgroup branches around them),
//    stored row-major to `so` as f32;
// 3. the online softmax, in f32: each row belongs to 8 lanes of one subgroup (row
//    r = sg * SG/8 + lane/8, lane j = lane % 8 owning keys j, j+8, ...), which take the tile's
//    maximum with three xor shuffles, rescale their running sums, and write P = exp(S*scale - m)
//    to `ps` as f16; the running sum adds the rounded P, so the weights that multiply V are
//    exactly the ones the output is divided by;
// 4. O_tile = P V: (BQ/F) x (DP/F) fragments, stored to `so` as f32 (S is consumed); where
//    there are fewer fragments than subgroups the keys are split among them (KS below);
// 5. each row's 8 lanes keep its running output in registers, features j, j+8, ..., and update
//    it as o = o * exp(m_old - m_new) + O_tile. WGSL cooperative matrices give no access to
//    their elements, so this rescaling is why O_tile goes through workgroup memory.
// Four barriers per tile. After the last tile each lane divides by the row's sum (its 8 lanes'
// partial sums, added by shuffles) and writes its features; lane 0 writes the log-sum-exp.
// A segment with no keys gets zeros and lse = -inf, as in the portable kernels.

// @include attention_common.wgsl

@group(0) @binding(0) var<storage, read> q: array<vec2<u32>>;
@group(0) @binding(1) var<storage, read> k: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> v: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read_write> o: array<f32>;
@group(0) @binding(7) var<storage, read_write> lse: array<f32>;

const BQ: u32 = 32u;
const D4: u32 = D / 4u;
// D rounded up to whole fragments; the features past D are zero in every staged tile.
const DP: u32 = (D + F - 1u) / F * F;
// Row strides: queries, keys and values (halves), P (halves), S (floats), O_tile (floats).
const RQ: u32 = DP + PAD_H;
const RP: u32 = BK + PAD_H;
const RS: u32 = BK + PAD_F;
const RO: u32 = DP + PAD_F;
// Invocations per subgroup, subgroups per workgroup.
const SG: u32 = F * F / 8u;
const NSG: u32 = 256u / SG;
// Fragments of S and of O_tile, and the rounds of subgroups that cover them.
const NSF: u32 = (BQ / F) * (BK / F);
const NOF: u32 = (BQ / F) * (DP / F);
const S_ROUNDS: u32 = (NSF + NSG - 1u) / NSG;
// Each subgroup computes the same S fragment every tile, which lets it keep its Q fragments.
const_assert S_ROUNDS == 1u;
// Where O_tile has fewer fragments than there are subgroups (narrow heads: D = 16 or 32), the
// keys of a tile are split into KS parts, each subgroup multiplying one part into its own
// partial O_tile, and the output pass adds the parts: no subgroup idles or repeats work.
// (NOF divides NSG whenever it is smaller, and BK / KS stays a multiple of F.)
const KS: u32 = max(1u, NSG / NOF);
const KB: u32 = BK / KS;
const O_ROUNDS: u32 = (NOF * KS + NSG - 1u) / NSG;
// `so` holds S, or the KS partial O_tiles; then one FxF scratch slot for the stores of spare
// subgroups.
const SO_MAIN: u32 = max(BQ * RS, KS * BQ * RO);

var<workgroup> qs: array<f16, BQ * RQ>;
var<workgroup> ks: array<f16, BK * RQ>;
var<workgroup> vs: array<f16, BK * RQ>;
var<workgroup> ps: array<f16, BQ * RP>;
var<workgroup> so: array<f32, SO_MAIN + F * F>;

fn unpack4(w: vec2<u32>) -> vec4<f16> {
    return vec4<f16>(vec2<f16>(unpack2x16float(w.x)), vec2<f16>(unpack2x16float(w.y)));
}

// Chunk i (4 features) of the staged tile of `rows` rows starting at row `first`, head h, of
// the tensor `which` (0 q, 1 k, 2 v): zero past `count` rows or past D features.
fn chunk(which: u32, first: u32, count: u32, h: u32, i: u32) -> vec4<f16> {
    let r = i / (DP / 4u);
    let c4 = i % (DP / 4u);
    if r < count && c4 < D4 {
        let src = ((first + r) * pc.heads + h) * D4 + c4;
        if which == 0u {
            return unpack4(q[src]);
        } else if which == 1u {
            return unpack4(k[src]);
        }
        return unpack4(v[src]);
    }
    return vec4<f16>(0.0h);
}

fn stage_q(first: u32, count: u32, h: u32, t: u32) {
    for (var i = t; i < BQ * DP / 4u; i += 256u) {
        let x = chunk(0u, first, count, h, i);
        let o0 = (i / (DP / 4u)) * RQ + (i % (DP / 4u)) * 4u;
        qs[o0] = x.x;
        qs[o0 + 1u] = x.y;
        qs[o0 + 2u] = x.z;
        qs[o0 + 3u] = x.w;
    }
}

fn stage_kv(first: u32, count: u32, h: u32, t: u32) {
    for (var i = t; i < BK * DP / 4u; i += 256u) {
        let o0 = (i / (DP / 4u)) * RQ + (i % (DP / 4u)) * 4u;
        let x = chunk(1u, first, count, h, i);
        ks[o0] = x.x;
        ks[o0 + 1u] = x.y;
        ks[o0 + 2u] = x.z;
        ks[o0 + 3u] = x.w;
        let y = chunk(2u, first, count, h, i);
        vs[o0] = y.x;
        vs[o0 + 1u] = y.y;
        vs[o0 + 2u] = y.z;
        vs[o0 + 3u] = y.w;
    }
}

// Where fragment f of a grid `cols` fragments wide, row stride `stride`, goes in `so`: its
// place, or the scratch slot (row stride F) when f is past the `count` fragments there are.
fn so_slot(f: u32, count: u32, cols: u32, stride: u32) -> vec2<u32> {
    let fc = min(f, count - 1u);
    let at = (fc / cols) * F * stride + (fc % cols) * F;
    return select(vec2<u32>(SO_MAIN, F), vec2<u32>(at, stride), f < count);
}

@compute @workgroup_size(256)
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
    // This lane's row and its place among the row's 8 lanes (softmax and output passes).
    let r = sg * (SG / 8u) + lane / 8u;
    let j = lane % 8u;

    // A zero fragment to start each product from (a variable declared without initialiser is
    // zero; copying it makes that explicit in every loop iteration).
    var zero: FragC;
    var m = neg_inf();
    var l = 0.0;
    var acc: array<f32, D / 8u>;
    for (var c = 0u; c < D / 8u; c++) {
        acc[c] = 0.0;
    }
    stage_q(q0, nrows, h, t);
    workgroupBarrier();
    // The S fragments of a subgroup keep their rows from tile to tile (one round: NSF <= NSG),
    // so its Q fragments are read from workgroup memory once, here, and kept.
    let q_rows = (min(sg, NSF - 1u) / (BK / F)) * F;
    var qf: array<FragA, DP / F>;
    for (var d = 0u; d < DP / F; d++) {
        qf[d] = coopLoadT<FragA>(&qs[q_rows * RQ + d * F], RQ);
    }

    for (var kt = k_begin; kt < k_end; kt += BK) {
        let count = min(BK, k_end - kt);
        // ks and vs were last read before the previous tile's third barrier; so was last written
        // by this tile's products, which follow the barrier below.
        stage_kv(kt, count, h, t);
        workgroupBarrier();

        // 2. S = Q K^T. K^T's fragment (k = feature, n = key) is K read column-major.
        for (var i = 0u; i < S_ROUNDS; i++) {
            let f = sg + i * NSG;
            let fc = min(f, NSF - 1u);
            let ci = (fc % (BK / F)) * F; // its rows are q_rows
            var s = zero;
            for (var d = 0u; d < DP / F; d++) {
                let b = coopLoad<FragB>(&ks[ci * RQ + d * F], RQ);
                s = coopMultiplyAdd(qf[d], b, s);
            }
            // naga 30 lowers coopStore without first emitting the expressions in its arguments,
            // so each argument is bound by an earlier `let`.
            let slot = so_slot(f, NSF, BK / F, RS);
            let value = s;
            let dst = &so[slot.x];
            let stride = slot.y;
            coopStoreT(value, dst, stride);
        }
        workgroupBarrier();

        // 3. Online softmax of row r over this tile's keys.
        var sv: array<f32, BK / 8u>;
        var tile_max = neg_inf();
        for (var i = 0u; i < BK / 8u; i++) {
            let key = j + 8u * i;
            sv[i] = select(neg_inf(), so[r * RS + key] * pc.scale, key < count);
            tile_max = max(tile_max, sv[i]);
        }
        tile_max = max(tile_max, subgroupShuffleXor(tile_max, 1u));
        tile_max = max(tile_max, subgroupShuffleXor(tile_max, 2u));
        tile_max = max(tile_max, subgroupShuffleXor(tile_max, 4u));
        let m_new = max(m, tile_max);
        let correction = exp(m - m_new);
        l *= correction;
        for (var i = 0u; i < BK / 8u; i++) {
            let p = f16(exp(sv[i] - m_new));
            ps[r * RP + j + 8u * i] = p;
            l += f32(p);
        }
        m = m_new;
        workgroupBarrier();

        // 4. O_tile = P V, in KS parts over the keys. V's fragment (k = key, n = feature) is V
        // read row-major.
        for (var i = 0u; i < O_ROUNDS; i++) {
            let f = sg + i * NSG;
            let fc = min(f, NOF * KS - 1u);
            let part = fc / NOF;
            let fo = fc % NOF;
            let ri = (fo / (DP / F)) * F;
            let ci = (fo % (DP / F)) * F;
            var acc_f = zero;
            for (var kk = part * KB; kk < (part + 1u) * KB; kk += F) {
                let a = coopLoadT<FragA>(&ps[ri * RP + kk], RP);
                let b = coopLoadT<FragB>(&vs[kk * RQ + ci], RQ);
                acc_f = coopMultiplyAdd(a, b, acc_f);
            }
            var slot = so_slot(fo, NOF, DP / F, RO);
            slot.x += part * BQ * RO;
            slot = select(vec2<u32>(SO_MAIN, F), slot, f < NOF * KS);
            let value = acc_f;
            let dst = &so[slot.x];
            let stride = slot.y;
            coopStoreT(value, dst, stride);
        }
        workgroupBarrier();

        // 5. Rescale the running output and add this tile's parts.
        for (var c = 0u; c < D / 8u; c++) {
            var tile = 0.0;
            for (var p = 0u; p < KS; p++) {
                tile += so[p * BQ * RO + r * RO + j + 8u * c];
            }
            acc[c] = acc[c] * correction + tile;
        }
    }

    l += subgroupShuffleXor(l, 1u);
    l += subgroupShuffleXor(l, 2u);
    l += subgroupShuffleXor(l, 4u);
    if r < nrows {
        let row = q0 + r;
        var inv = 0.0;
        var row_lse = neg_inf();
        if l > 0.0 {
            inv = 1.0 / l;
            row_lse = m + log(l);
        }
        for (var c = 0u; c < D / 8u; c++) {
            o[(row * pc.heads + h) * D + j + 8u * c] = acc[c] * inv;
        }
        if j == 0u {
            lse[row * pc.heads + h] = row_lse;
        }
    }
}
