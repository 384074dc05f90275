// Batched matrix multiply without workgroup memory or barriers, for products with a narrow
// side on CPU devices (lavapipe). There a workgroup runs as a loop over its groups of SIMD
// lanes, and every barrier switches between all of them: the narrow-tile kernel
// (matmul_small.wgsl) takes two per 16 steps of K. Here each invocation computes NC
// consecutive outputs of one row over all of K, reading A and B straight from device memory
// (the CPU's caches); B's row is the same for every invocation of a workgroup. On lavapipe 25
// this made 10000x32x128 2.0x faster than the 32x32-tile kernel and the 32x32x10000 weight
// gradient 1.9x, and the demo's training 31 % faster; 16 outputs an invocation beat 32 (too
// many accumulators for 16 vector registers). GPUs keep the tiled kernels, which reuse each
// loaded value across a tile.
//
// The same push constants, strides, bias and output layout as matmul.wgsl (see there); host
// side engine/src/ops/matmul.rs.

// @include matmul_params.wgsl

@group(0) @binding(0) var<storage, read> a: array<f32>;
@group(0) @binding(1) var<storage, read> b: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;
// [n] f32, added to each row when MATMUL_FLAG_BIAS is set (as in matmul.wgsl).
@group(0) @binding(3) var<storage, read> bias: array<f32>;
var<immediate> pc: Params;

// Outputs per invocation (consecutive columns), and rows per workgroup.
const NC: u32 = 16u;
const WG: u32 = 64u;

@compute @workgroup_size(64)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let z = wid.z + pc.batch_base;
    let row = wid.y * WG + lid;
    let col0 = wid.x * NC;
    if row >= pc.m || col0 >= pc.n {
        return;
    }
    // Columns past n read the last column again, and are not written.
    let last = pc.n - 1u - col0;
    var acc: array<f32, NC>;
    for (var j = 0u; j < NC; j++) {
        acc[j] = 0.0;
    }
    // MATMUL_FLAG_SUMMED: every batch entry's product summed into output 0 (a stack of linear
    // layers' input gradient, sum_i dY_i W_i^T, without a pass to add them up).
    let summed = (pc.flags & MATMUL_FLAG_SUMMED) != 0u;
    let entries = select(1u, pc.batch_base, summed);
    let first = select(z, 0u, summed);
    for (var e = 0u; e < entries; e++) {
        let a_at = (first + e) * pc.a_batch + row * pc.a_row;
        let b_at = (first + e) * pc.b_batch + col0 * pc.b_col;
        for (var kk = 0u; kk < pc.k; kk++) {
            let x = a[a_at + kk * pc.a_col];
            let b_row = b_at + kk * pc.b_row;
            for (var j = 0u; j < NC; j++) {
                acc[j] = fma(x, b[b_row + min(j, last) * pc.b_col], acc[j]);
            }
        }
    }
    let o_at = select(z, 0u, summed) * pc.m * pc.n + row * pc.n + col0;
    for (var j = 0u; j < min(NC, pc.n - col0); j++) {
        var x = acc[j];
        if (pc.flags & MATMUL_FLAG_BIAS) != 0u {
            x += bias[select(0u, z * pc.n, (pc.flags & MATMUL_FLAG_BIAS_PER_ENTRY) != 0u) + col0 + j];
        }
        if pc.accumulate != 0u {
            x += out[o_at + j];
        }
        out[o_at + j] = x;
    }
}
