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
// The same push constants, strides, flags, bias and output layout as matmul.wgsl (see
// matmul_params.wgsl); host side engine/src/ops/matmul.rs, which takes it only where the
// contiguous axes are multiples of 4: LAYOUT 0 (a [M, K], b [K, N]) and 2 (b [N, K]) need
// K and N so, LAYOUT 1 (a [K, M]) M and N. Needs subgroups of at least 8 lanes (one workgroup is
// then within one subgroup).

// @include matmul_params.wgsl

@group(0) @binding(0) var<storage, read> a: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> b: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> out: array<vec4<f32>>;
// [N] (or [batch, N] with MATMUL_FLAG_BIAS_PER_ENTRY), added to each row with MATMUL_FLAG_BIAS.
@group(0) @binding(3) var<storage, read> bias: array<vec4<f32>>;
var<immediate> pc: Params;

// 0: a [M, K] and b [K, N]; 1: a transposed, [K, M]; 2: b transposed, [N, K].
const LAYOUT: u32 = 0u;

@compute @workgroup_size(8)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let z = wid.z + pc.batch_base;
    let m4 = pc.m / 4u;
    let n4 = pc.n / 4u;
    let k4 = pc.k / 4u;
    let col4 = wid.x * 8u + lid;
    // Loads clamp to the last row or column; what they read there is never stored.
    let cl = min(col4, n4 - 1u);
    let r0 = wid.y * 8u;
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
        // Batch strides are in elements, multiples of 4 where this kernel runs.
        let za = (first + e) * (pc.a_batch / 4u);
        let zb = (first + e) * (pc.b_batch / 4u);
        for (var kb = 0u; kb < (pc.k + 3u) / 4u; kb++) {
            // The 8 x 4 block of A (rows r0.., k 4 kb..), a vec4 a lane.
            var av: vec4<f32>;
            if LAYOUT == 1u {
                // a [K, M]: lane l holds k = 4 kb + l / 2, rows r0 + 4 (l % 2) ..; past K, zeros.
                let kk = kb * 4u + lid / 2u;
                av = a[za + min(kk, pc.k - 1u) * m4 + min(r0 / 4u + lid % 2u, m4 - 1u)];
                av = select(vec4<f32>(0.0), av, kk < pc.k);
            } else {
                // a [M, K]: lane l holds row r0 + l, k 4 kb ..
                av = a[za + min(r0 + lid, pc.m - 1u) * k4 + kb];
            }
            // B at k = 4 kb + j, the lane's 4 columns.
            var b0: vec4<f32>;
            var b1: vec4<f32>;
            var b2: vec4<f32>;
            var b3: vec4<f32>;
            if LAYOUT == 2u {
                // b [N, K]: rows 4 cl + j of it hold the 4 k of column j; transpose the 4 x 4.
                let t0 = b[zb + min(cl * 4u + 0u, pc.n - 1u) * k4 + kb];
                let t1 = b[zb + min(cl * 4u + 1u, pc.n - 1u) * k4 + kb];
                let t2 = b[zb + min(cl * 4u + 2u, pc.n - 1u) * k4 + kb];
                let t3 = b[zb + min(cl * 4u + 3u, pc.n - 1u) * k4 + kb];
                b0 = vec4<f32>(t0.x, t1.x, t2.x, t3.x);
                b1 = vec4<f32>(t0.y, t1.y, t2.y, t3.y);
                b2 = vec4<f32>(t0.z, t1.z, t2.z, t3.z);
                b3 = vec4<f32>(t0.w, t1.w, t2.w, t3.w);
            } else {
                b0 = b[zb + min(kb * 4u + 0u, pc.k - 1u) * n4 + cl];
                b1 = b[zb + min(kb * 4u + 1u, pc.k - 1u) * n4 + cl];
                b2 = b[zb + min(kb * 4u + 2u, pc.k - 1u) * n4 + cl];
                b3 = b[zb + min(kb * 4u + 3u, pc.k - 1u) * n4 + cl];
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
    if col4 >= n4 {
        return;
    }
    let o = select(z, 0u, summed) * pc.m * n4 + col4;
    let bias_at = select(0u, z * n4, (pc.flags & MATMUL_FLAG_BIAS_PER_ENTRY) != 0u) + col4;
    store(r0 + 0u, o, bias_at, n4, c0);
    store(r0 + 1u, o, bias_at, n4, c1);
    store(r0 + 2u, o, bias_at, n4, c2);
    store(r0 + 3u, o, bias_at, n4, c3);
    store(r0 + 4u, o, bias_at, n4, c4);
    store(r0 + 5u, o, bias_at, n4, c5);
    store(r0 + 6u, o, bias_at, n4, c6);
    store(r0 + 7u, o, bias_at, n4, c7);
}

// Writes row `row`'s vec4 of outputs (skipped past M), with the bias and onto the output when
// accumulating.
fn store(row: u32, o: u32, bias_at: u32, n4: u32, value: vec4<f32>) {
    if row >= pc.m {
        return;
    }
    var x = value;
    if (pc.flags & MATMUL_FLAG_BIAS) != 0u {
        x += bias[bias_at];
    }
    let at = o + row * n4;
    if pc.accumulate != 0u {
        x += out[at];
    }
    out[at] = x;
}
