// @variants LAYOUT: 0 1 2
// Batched matrix multiply for CPU devices (lavapipe), where every storage access is a loop over
// the lanes of a SIMD group with a bounds check per lane (about 12 ns for 8 lanes, uniform or
// not, on lavapipe 25; an FMA costs 0.9 ns, a subgroup broadcast 1.5 ns): so the kernel moves
// data in vec4 accesses, one per lane, and shares what lanes load by subgroup broadcasts
// instead of loading it again. A workgroup is one SIMD group of 8 lanes computing 8 rows x 32
// columns: lane l owns 4 consecutive columns (a vec4 of B per k) and all 8 rows; per 4 k, each
// lane loads one vec4 of A (together the 8 x 4 block) and 4 of B, and takes each A value from
// the lane that holds it. On lavapipe 25 this ran 256^3 at 11.9 GFLOP/s and 10000x64x256 at
// 11.8, against 4.1 and 1.8 for the tiled and row kernels (docs/decisions/kernels.md).
//
// Any shape and layout runs: where an operand's contiguous axis is not a multiple of 4, its
// values are read one by one at the strides of the push constants (MATMUL_FLAG_A_SCALAR,
// MATMUL_FLAG_B_SCALAR), and where N is not, the outputs are written one by one. LAYOUT
// chooses the vec4 reads: 0, A along K ([M, K]) and B along N ([K, N]); 1, A along M ([K, M],
// transposed); 2, B along K ([N, K], transposed). The same push constants, strides, flags, bias
// and output layout as matmul.wgsl (matmul_params.wgsl); host side engine/src/ops/matmul.rs.
// Needs subgroups of at least 8 lanes (one workgroup is then within one subgroup).

// @include matmul_params.wgsl

@group(0) @binding(0) var<storage, read> a: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> b: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> out: array<vec4<f32>>;
// [N] (or [batch, N] with MATMUL_FLAG_BIAS_PER_ENTRY), added to each row with MATMUL_FLAG_BIAS.
@group(0) @binding(3) var<storage, read> bias: array<vec4<f32>>;
var<immediate> pc: Params;

const LAYOUT: u32 = 0u;

// One f32 of a vec4 array, by element index (the scalar paths).
fn a_at(i: u32) -> f32 {
    return a[i >> 2u][i & 3u];
}
fn b_at(i: u32) -> f32 {
    return b[i >> 2u][i & 3u];
}

@compute @workgroup_size(8)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let z = wid.z + pc.batch_base;
    let m4 = pc.m / 4u;
    let n4 = pc.n / 4u;
    let k4 = pc.k / 4u;
    // Groups of 4 columns (the last one partial where N is not a multiple of 4).
    let groups = (pc.n + 3u) / 4u;
    let col4 = wid.x * 8u + lid;
    // Loads clamp to the last row or column; what they read there is never stored.
    let cl = min(col4, groups - 1u);
    let r0 = wid.y * 8u;
    let a_scalar = (pc.flags & MATMUL_FLAG_A_SCALAR) != 0u;
    let b_scalar = (pc.flags & MATMUL_FLAG_B_SCALAR) != 0u;
    var c0 = vec4<f32>(0.0);
    var c1 = vec4<f32>(0.0);
    var c2 = vec4<f32>(0.0);
    var c3 = vec4<f32>(0.0);
    var c4 = vec4<f32>(0.0);
    var c5 = vec4<f32>(0.0);
    var c6 = vec4<f32>(0.0);
    var c7 = vec4<f32>(0.0);
    // MATMUL_FLAG_SUMMED: every batch entry's product summed into output 0.
    let summed = (pc.flags & MATMUL_FLAG_SUMMED) != 0u;
    let entries = select(1u, pc.batch_base, summed);
    let first = select(z, 0u, summed);
    for (var e = 0u; e < entries; e++) {
        // Batch offsets in elements (multiples of 4 on the vec4 paths).
        let za = (first + e) * pc.a_batch;
        let zb = (first + e) * pc.b_batch;
        for (var kb = 0u; kb < (pc.k + 3u) / 4u; kb++) {
            // The 8 x 4 block of A (rows r0.., k 4 kb..), a vec4 a lane.
            var av: vec4<f32>;
            if LAYOUT == 1u {
                // a [K, M]: lane l holds k = 4 kb + l / 2, rows r0 + 4 (l % 2) ..; past K, zeros.
                let kk = kb * 4u + lid / 2u;
                av = a[za / 4u + min(kk, pc.k - 1u) * m4 + min(r0 / 4u + lid % 2u, m4 - 1u)];
                av = select(vec4<f32>(0.0), av, kk < pc.k);
            } else if a_scalar {
                // Lane l holds row r0 + l, k 4 kb .. (zeros past K), at the push constants' strides.
                let at = za + min(r0 + lid, pc.m - 1u) * pc.a_row;
                for (var j = 0u; j < 4u; j++) {
                    let kk = kb * 4u + j;
                    av[j] = select(0.0, a_at(at + min(kk, pc.k - 1u) * pc.a_col), kk < pc.k);
                }
            } else {
                // a [M, K]: lane l holds row r0 + l, k 4 kb ..
                av = a[za / 4u + min(r0 + lid, pc.m - 1u) * k4 + kb];
            }
            // B at k = 4 kb + j, the lane's 4 columns.
            var b0: vec4<f32>;
            var b1: vec4<f32>;
            var b2: vec4<f32>;
            var b3: vec4<f32>;
            if LAYOUT == 2u {
                // b [N, K]: rows 4 cl + j of it hold the 4 k of column j; transpose the 4 x 4.
                let t0 = b[zb / 4u + min(cl * 4u + 0u, pc.n - 1u) * k4 + kb];
                let t1 = b[zb / 4u + min(cl * 4u + 1u, pc.n - 1u) * k4 + kb];
                let t2 = b[zb / 4u + min(cl * 4u + 2u, pc.n - 1u) * k4 + kb];
                let t3 = b[zb / 4u + min(cl * 4u + 3u, pc.n - 1u) * k4 + kb];
                b0 = vec4<f32>(t0.x, t1.x, t2.x, t3.x);
                b1 = vec4<f32>(t0.y, t1.y, t2.y, t3.y);
                b2 = vec4<f32>(t0.z, t1.z, t2.z, t3.z);
                b3 = vec4<f32>(t0.w, t1.w, t2.w, t3.w);
            } else if b_scalar {
                // One by one at the push constants' strides (A is zero past K, so a clamped k
                // reads a value that counts for nothing).
                var t: array<vec4<f32>, 4>;
                for (var j = 0u; j < 4u; j++) {
                    let row = zb + min(kb * 4u + j, pc.k - 1u) * pc.b_row;
                    for (var c = 0u; c < 4u; c++) {
                        t[j][c] = b_at(row + min(cl * 4u + c, pc.n - 1u) * pc.b_col);
                    }
                }
                b0 = t[0];
                b1 = t[1];
                b2 = t[2];
                b3 = t[3];
            } else {
                b0 = b[zb / 4u + min(kb * 4u + 0u, pc.k - 1u) * n4 + cl];
                b1 = b[zb / 4u + min(kb * 4u + 1u, pc.k - 1u) * n4 + cl];
                b2 = b[zb / 4u + min(kb * 4u + 2u, pc.k - 1u) * n4 + cl];
                b3 = b[zb / 4u + min(kb * 4u + 3u, pc.k - 1u) * n4 + cl];
            }
            // A[r0 + i, 4 kb + j] is lane i's component j (layouts 0, 2), or lane 2 j + i / 4's
            // component i % 4 (layout 1): broadcast from there, one row a line.
            // k = 4 kb + 0
            c0 = fma(vec4<f32>(select(subgroupBroadcast(av.x, 0u), subgroupBroadcast(av.x, 0u), LAYOUT == 1u)), b0, c0);
            c1 = fma(vec4<f32>(select(subgroupBroadcast(av.x, 1u), subgroupBroadcast(av.y, 0u), LAYOUT == 1u)), b0, c1);
            c2 = fma(vec4<f32>(select(subgroupBroadcast(av.x, 2u), subgroupBroadcast(av.z, 0u), LAYOUT == 1u)), b0, c2);
            c3 = fma(vec4<f32>(select(subgroupBroadcast(av.x, 3u), subgroupBroadcast(av.w, 0u), LAYOUT == 1u)), b0, c3);
            c4 = fma(vec4<f32>(select(subgroupBroadcast(av.x, 4u), subgroupBroadcast(av.x, 1u), LAYOUT == 1u)), b0, c4);
            c5 = fma(vec4<f32>(select(subgroupBroadcast(av.x, 5u), subgroupBroadcast(av.y, 1u), LAYOUT == 1u)), b0, c5);
            c6 = fma(vec4<f32>(select(subgroupBroadcast(av.x, 6u), subgroupBroadcast(av.z, 1u), LAYOUT == 1u)), b0, c6);
            c7 = fma(vec4<f32>(select(subgroupBroadcast(av.x, 7u), subgroupBroadcast(av.w, 1u), LAYOUT == 1u)), b0, c7);
            // k = 4 kb + 1
            c0 = fma(vec4<f32>(select(subgroupBroadcast(av.y, 0u), subgroupBroadcast(av.x, 2u), LAYOUT == 1u)), b1, c0);
            c1 = fma(vec4<f32>(select(subgroupBroadcast(av.y, 1u), subgroupBroadcast(av.y, 2u), LAYOUT == 1u)), b1, c1);
            c2 = fma(vec4<f32>(select(subgroupBroadcast(av.y, 2u), subgroupBroadcast(av.z, 2u), LAYOUT == 1u)), b1, c2);
            c3 = fma(vec4<f32>(select(subgroupBroadcast(av.y, 3u), subgroupBroadcast(av.w, 2u), LAYOUT == 1u)), b1, c3);
            c4 = fma(vec4<f32>(select(subgroupBroadcast(av.y, 4u), subgroupBroadcast(av.x, 3u), LAYOUT == 1u)), b1, c4);
            c5 = fma(vec4<f32>(select(subgroupBroadcast(av.y, 5u), subgroupBroadcast(av.y, 3u), LAYOUT == 1u)), b1, c5);
            c6 = fma(vec4<f32>(select(subgroupBroadcast(av.y, 6u), subgroupBroadcast(av.z, 3u), LAYOUT == 1u)), b1, c6);
            c7 = fma(vec4<f32>(select(subgroupBroadcast(av.y, 7u), subgroupBroadcast(av.w, 3u), LAYOUT == 1u)), b1, c7);
            // k = 4 kb + 2
            c0 = fma(vec4<f32>(select(subgroupBroadcast(av.z, 0u), subgroupBroadcast(av.x, 4u), LAYOUT == 1u)), b2, c0);
            c1 = fma(vec4<f32>(select(subgroupBroadcast(av.z, 1u), subgroupBroadcast(av.y, 4u), LAYOUT == 1u)), b2, c1);
            c2 = fma(vec4<f32>(select(subgroupBroadcast(av.z, 2u), subgroupBroadcast(av.z, 4u), LAYOUT == 1u)), b2, c2);
            c3 = fma(vec4<f32>(select(subgroupBroadcast(av.z, 3u), subgroupBroadcast(av.w, 4u), LAYOUT == 1u)), b2, c3);
            c4 = fma(vec4<f32>(select(subgroupBroadcast(av.z, 4u), subgroupBroadcast(av.x, 5u), LAYOUT == 1u)), b2, c4);
            c5 = fma(vec4<f32>(select(subgroupBroadcast(av.z, 5u), subgroupBroadcast(av.y, 5u), LAYOUT == 1u)), b2, c5);
            c6 = fma(vec4<f32>(select(subgroupBroadcast(av.z, 6u), subgroupBroadcast(av.z, 5u), LAYOUT == 1u)), b2, c6);
            c7 = fma(vec4<f32>(select(subgroupBroadcast(av.z, 7u), subgroupBroadcast(av.w, 5u), LAYOUT == 1u)), b2, c7);
            // k = 4 kb + 3
            c0 = fma(vec4<f32>(select(subgroupBroadcast(av.w, 0u), subgroupBroadcast(av.x, 6u), LAYOUT == 1u)), b3, c0);
            c1 = fma(vec4<f32>(select(subgroupBroadcast(av.w, 1u), subgroupBroadcast(av.y, 6u), LAYOUT == 1u)), b3, c1);
            c2 = fma(vec4<f32>(select(subgroupBroadcast(av.w, 2u), subgroupBroadcast(av.z, 6u), LAYOUT == 1u)), b3, c2);
            c3 = fma(vec4<f32>(select(subgroupBroadcast(av.w, 3u), subgroupBroadcast(av.w, 6u), LAYOUT == 1u)), b3, c3);
            c4 = fma(vec4<f32>(select(subgroupBroadcast(av.w, 4u), subgroupBroadcast(av.x, 7u), LAYOUT == 1u)), b3, c4);
            c5 = fma(vec4<f32>(select(subgroupBroadcast(av.w, 5u), subgroupBroadcast(av.y, 7u), LAYOUT == 1u)), b3, c5);
            c6 = fma(vec4<f32>(select(subgroupBroadcast(av.w, 6u), subgroupBroadcast(av.z, 7u), LAYOUT == 1u)), b3, c6);
            c7 = fma(vec4<f32>(select(subgroupBroadcast(av.w, 7u), subgroupBroadcast(av.w, 7u), LAYOUT == 1u)), b3, c7);
        }
    }
    if col4 >= groups {
        return;
    }
    let entry = select(z, 0u, summed);
    let bias_row = select(0u, z, (pc.flags & MATMUL_FLAG_BIAS_PER_ENTRY) != 0u);
    store(r0 + 0u, entry, bias_row, col4, c0);
    store(r0 + 1u, entry, bias_row, col4, c1);
    store(r0 + 2u, entry, bias_row, col4, c2);
    store(r0 + 3u, entry, bias_row, col4, c3);
    store(r0 + 4u, entry, bias_row, col4, c4);
    store(r0 + 5u, entry, bias_row, col4, c5);
    store(r0 + 6u, entry, bias_row, col4, c6);
    store(r0 + 7u, entry, bias_row, col4, c7);
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
