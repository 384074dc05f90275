// @variants LAYOUT: 0 1 2
// @variants COLS: 1 2 4
// Batched matrix multiply for CPU devices (lavapipe). There a storage-buffer read is a loop over
// the lanes of a SIMD group with a bounds check and a branch per lane, while a texel-buffer read
// is a branch-free gather (half the time for a vec4 on lavapipe 25), a subgroup shuffle is one
// permute, and an update of a variable inside a loop costs a blend with the loop's mask; there
// is no FMA (a multiply and an add). So the operands are read through texel buffers, a
// workgroup is one SIMD group of 8 lanes computing 8 rows x 32 COLS columns (lane l owns COLS
// vec4 groups of 4 columns, for all 8 rows), and per 8 k each lane reads its 8 vec4s of B per
// group and 2 vec4s of A, takes every A value from the lane that read it by a shuffle, and adds
// the 8 products into each accumulator in one expression (one write a block, not one a k).
// On lavapipe 25, one thread: 256^3 in 0.94 ms against 1.9 for the storage-buffer kernel this
// replaced (8 x 32, a write per 4 k), 10000x64x256 10.8 against 18.5 (docs/decisions/kernels.md).
//
// Any shape and layout runs: where an operand's contiguous axis is not a multiple of 4, its
// values are read one by one at the strides of the push constants (MATMUL_FLAG_A_SCALAR,
// MATMUL_FLAG_B_SCALAR), and where N is not, the outputs are written one by one. LAYOUT
// chooses the vec4 reads: 0, A along K ([M, K]) and B along N ([K, N]); 1, A along M ([K, M],
// transposed); 2, B along K ([N, K], transposed). COLS (1, 2, 4) fits the tile to narrow
// outputs. The same push constants, strides, flags, bias and output layout as matmul.wgsl
// (matmul_params.wgsl); host side engine/src/ops/matmul.rs. Needs subgroups of at least 8 lanes
// (one workgroup is then within one subgroup).

// @include matmul_params.wgsl

// A and B as texel buffers of vec4s (engine/build.rs): element i is component i % 4 of texel
// i / 4.
@group(0) @binding(0) var a: texture_storage_1d<rgba32float, read>;
@group(0) @binding(1) var b: texture_storage_1d<rgba32float, read>;
@group(0) @binding(2) var<storage, read_write> out: array<vec4<f32>>;
// [N] (or [batch, N] with MATMUL_FLAG_BIAS_PER_ENTRY), added to each row with MATMUL_FLAG_BIAS.
@group(0) @binding(3) var<storage, read> bias: array<vec4<f32>>;
var<immediate> pc: Params;

const LAYOUT: u32 = 0u;
const COLS: u32 = 4u;

// One f32 of an operand, by element index (the scalar paths).
fn a_at(i: u32) -> f32 {
    return textureLoad(a, i >> 2u)[i & 3u];
}
fn b_at(i: u32) -> f32 {
    return textureLoad(b, i >> 2u)[i & 3u];
}

// The 8 values of a row of A in a block of 8 k, in k order, every lane holding them all.
struct Row {
    k0: vec4<f32>,
    k1: vec4<f32>,
}

// B in a block of 8 k for one group of 4 columns: j0 at k, ... j7 at k + 7.
struct Block {
    j0: vec4<f32>,
    j1: vec4<f32>,
    j2: vec4<f32>,
    j3: vec4<f32>,
    j4: vec4<f32>,
    j5: vec4<f32>,
    j6: vec4<f32>,
    j7: vec4<f32>,
}

// Row r of the block from the lanes that read it: in layout 0 (and A's scalar path) lane r
// holds its row, k 0..3 in `av0` and 4..7 in `av1`; in layout 1 lane j holds k j, rows 0..3 in
// `av0` and 4..7 in `av1`.
fn row(av0: vec4<f32>, av1: vec4<f32>, r: u32) -> Row {
    if LAYOUT == 1u {
        let v = select(av1[r & 3u], av0[r & 3u], r < 4u);
        return Row(
            vec4<f32>(subgroupShuffle(v, 0u), subgroupShuffle(v, 1u), subgroupShuffle(v, 2u), subgroupShuffle(v, 3u)),
            vec4<f32>(subgroupShuffle(v, 4u), subgroupShuffle(v, 5u), subgroupShuffle(v, 6u), subgroupShuffle(v, 7u)),
        );
    }
    return Row(subgroupShuffle(av0, r), subgroupShuffle(av1, r));
}

// acc + the 8 products of a row with a block of B, in one expression.
fn step(acc: vec4<f32>, x: Row, bk: Block) -> vec4<f32> {
    return acc + x.k0.x * bk.j0 + x.k0.y * bk.j1 + x.k0.z * bk.j2 + x.k0.w * bk.j3
        + x.k1.x * bk.j4 + x.k1.y * bk.j5 + x.k1.z * bk.j6 + x.k1.w * bk.j7;
}

// B at k0 .. k0 + 7 for the group of columns 4 g .. 4 g + 3 (clamped: A is zero past K, so a
// clamped k reads a value that counts for nothing; columns past N are never stored).
fn block(zb: u32, k0: u32, g: u32) -> Block {
    var t: array<vec4<f32>, 8>;
    if LAYOUT == 2u {
        // b [N, K]: columns 4 g + q of the output are rows of b, 8 k = two texels each.
        let k4 = pc.k / 4u;
        let n_last = pc.n - 1u;
        let lo = min(k0 / 4u, k4 - 1u);
        let hi = min(k0 / 4u + 1u, k4 - 1u);
        var c0: array<vec4<f32>, 4>;
        var c1: array<vec4<f32>, 4>;
        for (var q = 0u; q < 4u; q++) {
            let at = zb / 4u + min(g * 4u + q, n_last) * k4;
            c0[q] = textureLoad(b, at + lo);
            c1[q] = textureLoad(b, at + hi);
        }
        for (var j = 0u; j < 4u; j++) {
            t[j] = vec4<f32>(c0[0][j], c0[1][j], c0[2][j], c0[3][j]);
            t[j + 4u] = vec4<f32>(c1[0][j], c1[1][j], c1[2][j], c1[3][j]);
        }
    } else if (pc.flags & MATMUL_FLAG_B_SCALAR) != 0u {
        // One by one at the push constants' strides.
        for (var j = 0u; j < 8u; j++) {
            let at = zb + min(k0 + j, pc.k - 1u) * pc.b_row;
            for (var c = 0u; c < 4u; c++) {
                t[j][c] = b_at(at + min(g * 4u + c, pc.n - 1u) * pc.b_col);
            }
        }
    } else {
        // b [K, N]: a texel per k.
        let n4 = pc.n / 4u;
        let col = min(g, n4 - 1u);
        for (var j = 0u; j < 8u; j++) {
            t[j] = textureLoad(b, zb / 4u + min(k0 + j, pc.k - 1u) * n4 + col);
        }
    }
    return Block(t[0], t[1], t[2], t[3], t[4], t[5], t[6], t[7]);
}

@compute @workgroup_size(8)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let z = wid.z + pc.batch_base;
    // Groups of 4 columns (the last one partial where N is not a multiple of 4): the lane's
    // first one, g0 .. g0 + COLS - 1 its own.
    let groups = (pc.n + 3u) / 4u;
    let g0 = (wid.x * 8u + lid) * COLS;
    let r0 = wid.y * 8u;
    let a_scalar = (pc.flags & MATMUL_FLAG_A_SCALAR) != 0u;
    // acc<row>_<column group>
    var acc0_0 = vec4<f32>(0.0); var acc0_1 = vec4<f32>(0.0); var acc0_2 = vec4<f32>(0.0); var acc0_3 = vec4<f32>(0.0);
    var acc1_0 = vec4<f32>(0.0); var acc1_1 = vec4<f32>(0.0); var acc1_2 = vec4<f32>(0.0); var acc1_3 = vec4<f32>(0.0);
    var acc2_0 = vec4<f32>(0.0); var acc2_1 = vec4<f32>(0.0); var acc2_2 = vec4<f32>(0.0); var acc2_3 = vec4<f32>(0.0);
    var acc3_0 = vec4<f32>(0.0); var acc3_1 = vec4<f32>(0.0); var acc3_2 = vec4<f32>(0.0); var acc3_3 = vec4<f32>(0.0);
    var acc4_0 = vec4<f32>(0.0); var acc4_1 = vec4<f32>(0.0); var acc4_2 = vec4<f32>(0.0); var acc4_3 = vec4<f32>(0.0);
    var acc5_0 = vec4<f32>(0.0); var acc5_1 = vec4<f32>(0.0); var acc5_2 = vec4<f32>(0.0); var acc5_3 = vec4<f32>(0.0);
    var acc6_0 = vec4<f32>(0.0); var acc6_1 = vec4<f32>(0.0); var acc6_2 = vec4<f32>(0.0); var acc6_3 = vec4<f32>(0.0);
    var acc7_0 = vec4<f32>(0.0); var acc7_1 = vec4<f32>(0.0); var acc7_2 = vec4<f32>(0.0); var acc7_3 = vec4<f32>(0.0);
    // MATMUL_FLAG_SUMMED: every batch entry's product summed into output 0.
    let summed = (pc.flags & MATMUL_FLAG_SUMMED) != 0u;
    let entries = select(1u, pc.batch_base, summed);
    let first = select(z, 0u, summed);
    for (var e = 0u; e < entries; e++) {
        // Batch offsets in elements (multiples of 4 on the vec4 paths).
        let za = (first + e) * pc.a_batch;
        let zb = (first + e) * pc.b_batch;
        for (var k0 = 0u; k0 < pc.k; k0 += 8u) {
            // A's block of 8 rows x 8 k, two vec4s a lane (see `row`); zeros past K.
            var av0: vec4<f32>;
            var av1: vec4<f32>;
            if LAYOUT == 1u {
                // a [K, M]: lane l holds k0 + l, rows r0 .. r0 + 7.
                let kk = k0 + lid;
                let m4 = pc.m / 4u;
                let at = za / 4u + min(kk, pc.k - 1u) * m4;
                av0 = select(vec4<f32>(0.0), textureLoad(a, at + min(r0 / 4u, m4 - 1u)), kk < pc.k);
                av1 = select(vec4<f32>(0.0), textureLoad(a, at + min(r0 / 4u + 1u, m4 - 1u)), kk < pc.k);
            } else if a_scalar {
                // Lane l holds row r0 + l, k0 .., at the push constants' strides.
                let at = za + min(r0 + lid, pc.m - 1u) * pc.a_row;
                for (var j = 0u; j < 4u; j++) {
                    av0[j] = select(0.0, a_at(at + min(k0 + j, pc.k - 1u) * pc.a_col), k0 + j < pc.k);
                    av1[j] = select(0.0, a_at(at + min(k0 + 4u + j, pc.k - 1u) * pc.a_col), k0 + 4u + j < pc.k);
                }
            } else {
                // a [M, K], K a multiple of 4: lane l holds row r0 + l, k0 .. k0 + 7.
                let k4 = pc.k / 4u;
                let at = za / 4u + min(r0 + lid, pc.m - 1u) * k4;
                av0 = textureLoad(a, at + k0 / 4u);
                av1 = select(vec4<f32>(0.0), textureLoad(a, at + min(k0 / 4u + 1u, k4 - 1u)), k0 + 4u < pc.k);
            }
            let x0 = row(av0, av1, 0u);
            let x1 = row(av0, av1, 1u);
            let x2 = row(av0, av1, 2u);
            let x3 = row(av0, av1, 3u);
            let x4 = row(av0, av1, 4u);
            let x5 = row(av0, av1, 5u);
            let x6 = row(av0, av1, 6u);
            let x7 = row(av0, av1, 7u);
            // Every block of B first, then the rows one after another: on lavapipe this order
            // ran 256^3 in 0.97 ms, a block's 8 rows after each block 1.23.
            let b0 = block(zb, k0, g0);
            var b1 = b0;
            var b2 = b0;
            var b3 = b0;
            if COLS >= 2u {
                b1 = block(zb, k0, g0 + 1u);
            }
            if COLS >= 4u {
                b2 = block(zb, k0, g0 + 2u);
                b3 = block(zb, k0, g0 + 3u);
            }
            acc0_0 = step(acc0_0, x0, b0);
            if COLS >= 2u { acc0_1 = step(acc0_1, x0, b1); }
            if COLS >= 4u { acc0_2 = step(acc0_2, x0, b2); acc0_3 = step(acc0_3, x0, b3); }
            acc1_0 = step(acc1_0, x1, b0);
            if COLS >= 2u { acc1_1 = step(acc1_1, x1, b1); }
            if COLS >= 4u { acc1_2 = step(acc1_2, x1, b2); acc1_3 = step(acc1_3, x1, b3); }
            acc2_0 = step(acc2_0, x2, b0);
            if COLS >= 2u { acc2_1 = step(acc2_1, x2, b1); }
            if COLS >= 4u { acc2_2 = step(acc2_2, x2, b2); acc2_3 = step(acc2_3, x2, b3); }
            acc3_0 = step(acc3_0, x3, b0);
            if COLS >= 2u { acc3_1 = step(acc3_1, x3, b1); }
            if COLS >= 4u { acc3_2 = step(acc3_2, x3, b2); acc3_3 = step(acc3_3, x3, b3); }
            acc4_0 = step(acc4_0, x4, b0);
            if COLS >= 2u { acc4_1 = step(acc4_1, x4, b1); }
            if COLS >= 4u { acc4_2 = step(acc4_2, x4, b2); acc4_3 = step(acc4_3, x4, b3); }
            acc5_0 = step(acc5_0, x5, b0);
            if COLS >= 2u { acc5_1 = step(acc5_1, x5, b1); }
            if COLS >= 4u { acc5_2 = step(acc5_2, x5, b2); acc5_3 = step(acc5_3, x5, b3); }
            acc6_0 = step(acc6_0, x6, b0);
            if COLS >= 2u { acc6_1 = step(acc6_1, x6, b1); }
            if COLS >= 4u { acc6_2 = step(acc6_2, x6, b2); acc6_3 = step(acc6_3, x6, b3); }
            acc7_0 = step(acc7_0, x7, b0);
            if COLS >= 2u { acc7_1 = step(acc7_1, x7, b1); }
            if COLS >= 4u { acc7_2 = step(acc7_2, x7, b2); acc7_3 = step(acc7_3, x7, b3); }
        }
    }
    let entry = select(z, 0u, summed);
    let bias_row = select(0u, z, (pc.flags & MATMUL_FLAG_BIAS_PER_ENTRY) != 0u);
    let g = array<u32, 4>(g0, g0 + 1u, g0 + 2u, g0 + 3u);
    for (var c = 0u; c < COLS; c++) {
        if g[c] >= groups {
            break;
        }
        var v: array<vec4<f32>, 8>;
        switch c {
            case 0u: { v = array(acc0_0, acc1_0, acc2_0, acc3_0, acc4_0, acc5_0, acc6_0, acc7_0); }
            case 1u: { v = array(acc0_1, acc1_1, acc2_1, acc3_1, acc4_1, acc5_1, acc6_1, acc7_1); }
            case 2u: { v = array(acc0_2, acc1_2, acc2_2, acc3_2, acc4_2, acc5_2, acc6_2, acc7_2); }
            default: { v = array(acc0_3, acc1_3, acc2_3, acc3_3, acc4_3, acc5_3, acc6_3, acc7_3); }
        }
        for (var r = 0u; r < 8u; r++) {
            store(r0 + r, entry, bias_row, g[c], v[r]);
        }
    }
}

// Writes row `row`'s 4 outputs from column 4 col4 (skipped past M, and past N one by one), with
// the bias and onto the output when accumulating.
fn store(row: u32, entry: u32, bias_row: u32, col4: u32, value: vec4<f32>) {
    if row >= pc.m {
        return;
    }
    let with_bias = (pc.flags & MATMUL_FLAG_BIAS) != 0u;
    if pc.n % 4u == 0u {
        let n4 = pc.n / 4u;
        var x = value;
        if with_bias {
            x += bias[bias_row * n4 + col4];
        }
        let at = (entry * pc.m + row) * n4 + col4;
        if pc.accumulate != 0u {
            x += out[at];
        }
        out[at] = x;
        return;
    }
    for (var c = 0u; c < 4u; c++) {
        let col = col4 * 4u + c;
        if col < pc.n {
            var x = value[c];
            if with_bias {
                let bi = bias_row * pc.n + col;
                x += bias[bi >> 2u][bi & 3u];
            }
            let at = (entry * pc.m + row) * pc.n + col;
            if pc.accumulate != 0u {
                x += out[at >> 2u][at & 3u];
            }
            out[at >> 2u][at & 3u] = x;
        }
    }
}
