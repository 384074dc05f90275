// Batched f16 matmul on cooperative matrices: 8x8x8 fragments, subgroups of 8 (lavapipe from
// Mesa 26 on, which offers only this shape). 128x128 output tile, k step 16, 32 KiB of
// workgroup memory (24 KiB of operand tiles, 8 KiB to stage edge fragments), within lavapipe's
// 32 KiB. The kernel and its description: include/matmul_coop_body.wgsl.

// @subgroup_size 8
enable f16;
enable wgpu_cooperative_matrix;

alias FragA = coop_mat8x8<f16, A>;
alias FragB = coop_mat8x8<f16, B>;
alias FragC = coop_mat8x8<f32, C>;
const F: u32 = 8u;
const BK: u32 = 16u;
// Row strides (halves) of the "along-k" and "along-r" tile layouts: 48 and 272 bytes.
const RS_K: u32 = 24u;
const RS_R: u32 = 136u;
// Halves per operand tile: the larger of 128 * 24 and 16 * 136.
const REGION: u32 = 3072u;

// @include matmul_coop_body.wgsl
