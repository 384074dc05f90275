// @variants D: 16 32 64 72
// Fused segment attention, backward (dq, then dk and dv), on f16 q, k, v with cooperative
// matrices: 8x8x8 fragments and subgroups of 8 (lavapipe from Mesa 26), blocks of 32 owned
// rows (four subgroups), tiles of 32 rows of the other side, no row padding: at most 31 KiB of
// workgroup memory (D = 72, dk/dv), within lavapipe's 32 KiB. The kernels and their
// description: include/attention_coop_backward_body.wgsl.

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

// @include attention_coop_backward_body.wgsl
