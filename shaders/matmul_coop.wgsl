// @variants ROWS, COLS, FRAG_COLS: 64 64 2, 64 128 2, 128 64 2, 128 128 2, 128 128 4
// Batched f16 matmul on cooperative matrices: 16x16x16 fragments, subgroups of 32 (NVIDIA),
// k step 32, output tiles of ROWS x COLS, 4 x FRAG_COLS fragments a subgroup. The 128x128
// variant takes 48 KiB of workgroup memory in 4x2 blocks (40 KiB of operand tiles, 8 KiB to
// stage edge fragments), 44 KiB in 4x4 blocks (64 x 64 a subgroup, half the subgroups); the
// 128x64 and 64x128 ones 34 KiB, the 64x64 one 22 KiB. The kernel and its description:
// include/matmul_coop_body.wgsl.

// @subgroup_size 32
enable f16;
enable wgpu_cooperative_matrix;

alias FragA = coop_mat16x16<f16, A>;
alias FragB = coop_mat16x16<f16, B>;
alias FragC = coop_mat16x16<f32, C>;
const F: u32 = 16u;
const BK: u32 = 32u;
const ROWS: u32 = 128u;
const COLS: u32 = 128u;
const FRAG_COLS: u32 = 2u;

// @include matmul_coop_body.wgsl
