// @variants D: 16 32 64 72
// @variants BQ: 32 64
// @variants BK: 32 64
// Fused segment attention, forward, on f16 q, k, v with cooperative matrices: 8x8x8 fragments
// and subgroups of 8 (lavapipe from Mesa 26 on), tiles of 32 or 64 keys, blocks of 32 or 64
// query rows (one subgroup per 8), no row padding: with 32-key tiles at most 30 KiB of
// workgroup memory (D = 72, 64 rows), within lavapipe's 32 KiB; 64-key tiles fit there in
// blocks of 32 at D = 16 and 32 (28 KiB). The kernel and its description:
// include/attention_coop_body.wgsl.

// @subgroup_size 8
enable f16;
enable wgpu_cooperative_matrix;

alias FragA = coop_mat8x8<f16, A>;
alias FragB = coop_mat8x8<f16, B>;
alias FragC = coop_mat8x8<f32, C>;
const D: u32 = 32u;
const BQ: u32 = 32u;
const F: u32 = 8u;
const BK: u32 = 32u;
const PAD_H: u32 = 0u;
const PAD_F: u32 = 0u;

// @include attention_coop_body.wgsl
