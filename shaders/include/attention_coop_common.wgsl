// What the cooperative-matrix attention kernels share: the f16 inputs, the shapes that follow
// from the fragment size, workgroup memory for staged rows and for each subgroup's f32 scores,
// and the staging and fragment-spilling helpers. Included by attention_coop_body.wgsl (the
// forward pass) and attention_coop_backward_body.wgsl, after attention_common.wgsl.
//
// The front file defines FragA, FragB, FragC, F (fragment size), D (head width), BQ (the rows a
// workgroup owns: queries in the forward pass and in dq, keys in dk/dv), BK (the rows of the
// other side per staged tile: keys, or queries in dk/dv), PAD_H and PAD_F (row padding of the
// f16 and f32 tiles, in elements, which spreads rows over the banks). The body defines
// `load_rows(which, src)`, the element `src` of its tensor `which` as f16.

@group(0) @binding(0) var<storage, read> q: array<vec2<u32>>;
@group(0) @binding(1) var<storage, read> k: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> v: array<vec2<u32>>;

const D4: u32 = D / 4u;
// D rounded up to whole fragments; the features past D are zero in every staged tile.
const DP: u32 = (D + F - 1u) / F * F;
// Fragments across a head (DF) and across a staged tile (KF).
const DF: u32 = DP / F;
const KF: u32 = BK / F;
// Row strides: staged rows (halves), a subgroup's f32 scores (floats) and f16 weights (halves).
const RQ: u32 = DP + PAD_H;
const RS: u32 = BK + PAD_F;
const RP: u32 = BK + PAD_H;
// Invocations per subgroup, subgroups (one per F owned rows) and invocations per workgroup.
const SG: u32 = F * F / 8u;
const NSG: u32 = BQ / F;
const WG: u32 = NSG * SG;
// Lanes per owned row in the row-wise steps, and the tile's columns each of them takes.
const LPR: u32 = SG / F;
const KPL: u32 = BK / LPR;
// One staged tile of rows, in halves. `kv` holds two tiles of each of two tensors (A0, B0,
// A1, B1: a double buffer); the owned rows are staged through it once, before the first tile.
const KV_TILE: u32 = BK * RQ;

// Four halves an element, so that a chunk of four features is one store. Offsets into it are
// reckoned in halves and divided by 4 at each access: every row stride (RQ) and fragment
// origin is a multiple of 8 halves, and cooperative loads read the vec4<f16> elements with
// strides in their units.
var<workgroup> kv: array<vec4<f16>, KV_TILE>;
// Each subgroup's F rows of f32 scores, S (or S^T), and the output on its way out.
var<workgroup> so: array<f32, NSG * F * RS>;
// Each subgroup's F rows of f16 weights: P (forward), dS (dq), P^T (dk/dv).
var<workgroup> ps: array<f16, NSG * F * RP>;

// Four halves of two packed words (the f32 round trip is a bitcast in the SPIR-V: see
// `bitcast_unpacked_halves` in engine/build.rs).
fn unpack4(w: vec2<u32>) -> vec4<f16> {
    return vec4<f16>(vec2<f16>(unpack2x16float(w.x)), vec2<f16>(unpack2x16float(w.y)));
}

// Chunk i (4 features) of the staged tile of rows starting at row `first`, head h, of the
// tensor `which` (see `load_rows`): zero past `count` rows or past D features.
fn chunk(which: u32, first: u32, count: u32, h: u32, i: u32) -> vec4<f16> {
    let r = i / (DP / 4u);
    let c4 = i % (DP / 4u);
    if r < count && c4 < D4 {
        return load_rows(which, ((first + r) * pc.heads + h) * D4 + c4);
    }
    return vec4<f16>(0.0h);
}

// Stages `rows` rows of tensor `which` from row `first` (`count` of them real) into kv at `at`.
fn stage(which: u32, first: u32, count: u32, h: u32, at: u32, rows: u32, t: u32) {
    for (var i = t; i < rows * DP / 4u; i += WG) {
        let x = chunk(which, first, count, h, i);
        kv[(at + (i / (DP / 4u)) * RQ) / 4u + i % (DP / 4u)] = x;
    }
}

// Stages the tile of BK rows starting at row `first` (of rows up to `end`) of tensors `a` and
// `b` into half `half` of kv: the keys and values of a forward or dq tile, the queries and
// output gradients of a dk/dv tile.
fn stage_pair(a: u32, b: u32, first: u32, end: u32, h: u32, half: u32, t: u32) {
    let count = min(BK, end - first);
    stage(a, first, count, h, half * 2u * KV_TILE, BK, t);
    stage(b, first, count, h, half * 2u * KV_TILE + KV_TILE, BK, t);
}

// Stores accumulator fragments d0 .. d0 + KF - 1 side by side into the subgroup's rows of `so`
// at `s_at` (row stride RS), for a pass over their elements. Past DF it stores the last
// fragment again: a spare copy, which is scaled and read back alike, instead of a branch
// around a cooperative operation. naga 30 lowers coopStore without first emitting the
// expressions in its arguments, so each argument is bound by an earlier `let`.
fn store_round(acc: ptr<function, array<FragC, DF>>, d0: u32, s_at: u32) {
    for (var x = 0u; x < KF; x++) {
        let value = (*acc)[min(d0 + x, DF - 1u)];
        let dst = &so[s_at + x * F];
        let stride = RS;
        coopStoreT(value, dst, stride);
    }
}

// `store_round` between two barriers: the previous reads of the subgroup's rows of `so` are
// done before the stores, and the stores before the reads that follow.
fn spill(acc: ptr<function, array<FragC, DF>>, d0: u32, s_at: u32) {
    workgroupBarrier();
    store_round(acc, d0, s_at);
    workgroupBarrier();
}
