// Batched f16 matmul on cooperative matrices: 16x16x16 fragments, subgroups of 32 (NVIDIA).
// 128x128 output tile, k step 32, 48 KiB of workgroup memory (40 KiB of operand tiles, 8 KiB to
// stage edge fragments). The kernel and its description: include/matmul_coop_body.wgsl.

// @subgroup_size 32
enable f16;
enable wgpu_cooperative_matrix;

alias FragA = coop_mat16x16<f16, A>;
alias FragB = coop_mat16x16<f16, B>;
alias FragC = coop_mat16x16<f32, C>;
const F: u32 = 16u;
const BK: u32 = 32u;
// Row strides (halves) of the "along-k" and "along-r" tile layouts: 80 and 272 bytes, so 8
// consecutive rows start at 8 different 16-byte offsets modulo 128 bytes.
const RS_K: u32 = 40u;
const RS_R: u32 = 136u;
// Halves per operand tile: the larger of 128 * 40 and 32 * 136.
const REGION: u32 = 5120u;

// @include matmul_coop_body.wgsl
