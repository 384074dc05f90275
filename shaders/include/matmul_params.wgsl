// The push constants of the matmul kernels (`matmul.wgsl`, `matmul_small.wgsl`,
// `matmul_coop.wgsl`), mirrored by `Params` in engine/src/ops/matmul.rs, and their flag bits. Strides are in
// elements; a batch stride of 0 broadcasts an operand over the batch.

// A is transposed ([K, M] in memory). The tiled f32 kernels use the strides alone; the
// cooperative-matrix kernel switches layouts on this and MATMUL_FLAG_TRANS_B.
const MATMUL_FLAG_TRANS_A: u32 = 1u;
// B is transposed ([N, K] in memory).
const MATMUL_FLAG_TRANS_B: u32 = 2u;
// Tiled and narrow-tile kernels: add bias[j] (binding 3) to every output of column j.
const MATMUL_FLAG_BIAS: u32 = 4u;
// matmul_rows.wgsl: sum the products of the batch entries into one [M, N] output,
// `batch_base` of them, in one dispatch of one z layer.
const MATMUL_FLAG_SUMMED: u32 = 8u;
// matmul_rows.wgsl, with MATMUL_FLAG_BIAS: the bias holds a row per batch entry, [batch, N].
const MATMUL_FLAG_BIAS_PER_ENTRY: u32 = 16u;
// matmul_cpu.wgsl: read A (B) one value at a time, at the strides (its contiguous axis is not
// a multiple of 4).
const MATMUL_FLAG_A_SCALAR: u32 = 32u;
const MATMUL_FLAG_B_SCALAR: u32 = 64u;

struct Params {
    m: u32,
    n: u32,
    k: u32,
    accumulate: u32,
    a_row: u32,
    a_col: u32,
    a_batch: u32,
    b_row: u32,
    b_col: u32,
    b_batch: u32,
    // The MATMUL_FLAG_* bits above (engine/build.rs gives them to the host side by name).
    flags: u32,
    batch_base: u32, // first batch entry of this dispatch (batches beyond the z limit are split)
}
