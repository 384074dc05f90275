// The push constants of the matmul kernels (`matmul.wgsl`, `matmul_small.wgsl`,
// `matmul_coop.wgsl`), mirrored by `Params` in engine/src/ops/matmul.rs. Strides are in
// elements; a batch stride of 0 broadcasts an operand over the batch.

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
    // Bit 0: A is transposed ([K, M] in memory); bit 1: B is transposed ([N, K]). The tiled f32
    // kernel uses the strides alone; the cooperative-matrix kernel switches layouts on them.
    // Bit 2 (tiled and narrow-tile kernels): add bias[j] (binding 3) to every output of column j.
    // Bit 3 (matmul_rows.wgsl): sum the products of the batch entries into one [M, N] output,
    // `batch_base` of them, in one dispatch of one z layer.
    // Bit 4 (matmul_rows.wgsl, with bit 2): the bias holds a row per batch entry, [batch, N].
    flags: u32,
    batch_base: u32, // first batch entry of this dispatch (batches beyond the z limit are split)
}
