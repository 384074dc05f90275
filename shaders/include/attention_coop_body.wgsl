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
// one head. The queries are staged into workgroup memory as f16 once, and each subgroup keeps
// the Q fragments of its S rows in registers; its output fragments (the running, unnormalised
// O) also stay in registers from the first key tile to the last. For each tile of BK keys:
// 1. the keys and values are staged into workgroup memory as f16 (rows past the segment and
//    features past D zero);
// 2. S = Q K^T: (BQ/F) x (BK/F) fragments, one per subgroup (or, where there are fewer
//    fragments than subgroups, a copy stored to a scratch slot: naga wants every cooperative
//    operation in uniform control flow, so no subgroup branches around them), stored
//    row-major to `so` as f32;
// 3. the online softmax, in f32: each row belongs to 8 lanes of one subgroup (row
//    r = sg * SG/8 + lane/8, lane j = lane % 8 owning keys j, j+8, ...), which take the tile's
//    maximum with three xor shuffles. The running maximum m moves lazily: only when some row's
//    tile maximum exceeds its m by more than RESCALE_MARGIN, and then for every row at once (a
//    workgroup vote read by workgroupUniformLoad, so the decision is uniform). Moving it
//    rescales the output fragments, through workgroup memory since WGSL cooperative matrices
//    give no element access; with typical scores that happens on the first tile only.
//    P = exp(S*scale - m) (below e^8) goes to `ps` as f16, and the running sum adds the
//    rounded P, so the weights that multiply V are exactly the ones the output is divided by;
// 4. O += P V on the output fragments. Where O has fewer fragments than there are subgroups
//    (D = 16 or 32) the tile's keys are split KS ways, each subgroup holding a partial O.
// Five barriers per tile. After the last tile the partial outputs go through workgroup memory;
// each row's lanes add them, divide by the row's sum (its 8 lanes' partial sums, added by
// shuffles) and write their features j, j+8, ...; lane 0 writes the log-sum-exp. A segment
// with no keys gets zeros and lse = -inf, as in the portable kernels.

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
// Whether any row wants to move the running maxima, for even and odd tiles (step 3).
var<workgroup> rescale_flags: array<atomic<u32>, 2>;

// How far a score may exceed the running maximum before the maxima move: P stays below
// e^8 (about 3000), far inside f16's range, with f16's relative precision.
const RESCALE_MARGIN: f32 = 8.0;

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

// Where subgroup fragment f (sg + round * NSG) of the output keeps its values in `so`: its part's
// partial tile, or the scratch slot for spare subgroups.
fn o_slot(f: u32) -> vec2<u32> {
    let fc = min(f, NOF * KS - 1u);
    var slot = so_slot(fc % NOF, NOF, DP / F, RO);
    slot.x += (fc / NOF) * BQ * RO;
    return select(vec2<u32>(SO_MAIN, F), slot, f < NOF * KS);
}

// Stores output fragment f (sg + round * NSG) to its place in `so` (see o_slot). naga 30
// lowers coopStore without first emitting the expressions in its arguments, so each argument
// is bound by an earlier `let`.
fn store_o(value: FragC, f: u32) {
    let slot = o_slot(f);
    let dst = &so[slot.x];
    let stride = slot.y;
    coopStoreT(value, dst, stride);
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
    // zero; copying it makes that explicit).
    var zero: FragC;
    var m = neg_inf();
    var l = 0.0;
    stage_q(q0, nrows, h, t);
    // Workgroup memory starts undefined: clear the flags of step 3 before the first tile.
    if t == 0u {
        atomicStore(&rescale_flags[0], 0u);
        atomicStore(&rescale_flags[1], 0u);
    }
    workgroupBarrier();
    // The S fragments of a subgroup keep their rows from tile to tile (one round: NSF <= NSG),
    // so its Q fragments are read from workgroup memory once, here, and kept.
    let q_rows = (min(sg, NSF - 1u) / (BK / F)) * F;
    var qf: array<FragA, DP / F>;
    for (var d = 0u; d < DP / F; d++) {
        qf[d] = coopLoadT<FragA>(&qs[q_rows * RQ + d * F], RQ);
    }
    // Likewise each subgroup's output fragments (and key part) are the same for every tile: the
    // running output stays in them, in registers, across all tiles.
    var oacc: array<FragC, O_ROUNDS>;
    for (var i = 0u; i < O_ROUNDS; i++) {
        oacc[i] = zero;
    }

    for (var kt = k_begin; kt < k_end; kt += BK) {
        let count = min(BK, k_end - kt);
        // ks, vs and ps were last read before the previous tile's last barrier.
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

        // 3. Online softmax of row r over this tile's keys, with a lazy maximum: the running
        // maximum m moves only when a score exceeds it by more than RESCALE_MARGIN, and then
        // for every row of the block at once (the decision must be uniform, since rescaling
        // touches the output fragments). Until then P = exp(S - m) stays below e^8, well
        // inside f16.
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
        // Tiles alternate between two flags: this tile's is raised by the subgroups that want
        // to move, read by all after a barrier (a uniform decision), and the other one,
        // last read a tile ago, is cleared for the next tile.
        let parity = ((kt - k_begin) / BK) & 1u;
        let wants = subgroupAny(tile_max > m + RESCALE_MARGIN);
        if lane == 0u && wants {
            atomicOr(&rescale_flags[parity], 1u);
        }
        if t == 0u {
            atomicStore(&rescale_flags[parity ^ 1u], 0u);
        }
        let rescale = workgroupUniformLoad(&rescale_flags[parity]) != 0u;
        let m_new = select(m, max(m, tile_max), rescale);
        let correction = exp(m - m_new);
        l *= correction;
        for (var i = 0u; i < BK / 8u; i++) {
            let p = f16(exp(sv[i] - m_new));
            ps[r * RP + j + 8u * i] = p;
            l += f32(p);
        }
        m = m_new;
        // Rescaling the output fragments goes through workgroup memory (no element access):
        // every S score was read before the vote's barrier, so `so` is free. (The first tile
        // always moves the maxima from -inf and scales the zero output by zero: naga cannot
        // prove a test of the loop counter uniform, so that one round trip stays.)
        if rescale {
            for (var i = 0u; i < O_ROUNDS; i++) {
                store_o(oacc[i], sg + i * NSG);
            }
            workgroupBarrier();
            for (var p = 0u; p < KS; p++) {
                for (var c = 0u; c < D / 8u; c++) {
                    let e = p * BQ * RO + r * RO + j + 8u * c;
                    so[e] *= correction;
                }
            }
            workgroupBarrier();
            for (var i = 0u; i < O_ROUNDS; i++) {
                let slot = o_slot(sg + i * NSG);
                oacc[i] = coopLoadT<FragC>(&so[slot.x], slot.y);
            }
        }
        workgroupBarrier();

        // 4. O += P V, in KS parts over the keys. V's fragment (k = key, n = feature) is V read
        // row-major.
        for (var i = 0u; i < O_ROUNDS; i++) {
            let fc = min(sg + i * NSG, NOF * KS - 1u);
            let part = fc / NOF;
            let fo = fc % NOF;
            let ri = (fo / (DP / F)) * F;
            let ci = (fo % (DP / F)) * F;
            for (var kk = part * KB; kk < (part + 1u) * KB; kk += F) {
                let a = coopLoadT<FragA>(&ps[ri * RP + kk], RP);
                let b = coopLoadT<FragB>(&vs[kk * RQ + ci], RQ);
                oacc[i] = coopMultiplyAdd(a, b, oacc[i]);
            }
        }
        // The next tile's staging overwrites ks, vs and ps.
        workgroupBarrier();
    }

    // 5. The output: the KS partial outputs through workgroup memory, summed per row.
    for (var i = 0u; i < O_ROUNDS; i++) {
        store_o(oacc[i], sg + i * NSG);
    }
    workgroupBarrier();
    var acc: array<f32, D / 8u>;
    for (var c = 0u; c < D / 8u; c++) {
        acc[c] = 0.0;
        for (var p = 0u; p < KS; p++) {
            acc[c] += so[p * BQ * RO + r * RO + j + 8u * c];
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
