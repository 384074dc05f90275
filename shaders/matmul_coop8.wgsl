// @variants ROWS, COLS, FRAG_COLS: 64 64 2, 64 128 2, 128 64 2, 128 128 2, 128 128 4
// Batched f16 matmul on cooperative matrices: 8x8x8 fragments, subgroups of 8 (lavapipe from
// Mesa 26 on, which offers only this shape), k step 16, output tiles of ROWS x COLS, 4 x
// FRAG_COLS fragments a subgroup. The 128x128 variant takes 32 KiB of workgroup memory in 4x2
// blocks (24 KiB of operand tiles, 8 KiB to stage edge fragments), within lavapipe's 32 KiB,
// and 28 KiB in 4x4 blocks; the smaller tiles take less. The kernel and its description:
// include/matmul_coop_body.wgsl.

// @subgroup_size 8
enable f16;
enable wgpu_cooperative_matrix;

alias FragA = coop_mat8x8<f16, A>;
alias FragB = coop_mat8x8<f16, B>;
alias FragC = coop_mat8x8<f32, C>;
const F: u32 = 8u;
const BK: u32 = 16u;
const ROWS: u32 = 128u;
const COLS: u32 = 128u;
const FRAG_COLS: u32 = 2u;

// @include matmul_coop_body.wgsl
