// @variants D: 16 32 64 72
// Fused segment attention, backward (dq, then dk and dv), on f16 q, k, v with cooperative
// matrices: 16x16x16 fragments and subgroups of 32 (NVIDIA), blocks of 32 owned rows (two
// subgroups), tiles of 32 rows of the other side. Workgroup memory: 37 KiB at D = 72 (dk/dv),
// within the 48 KiB NVIDIA offers. The kernels and their description:
// include/attention_coop_backward_body.wgsl.

// @subgroup_size 32
enable f16;
enable wgpu_cooperative_matrix;

alias FragA = coop_mat16x16<f16, A>;
alias FragB = coop_mat16x16<f16, B>;
alias FragC = coop_mat16x16<f32, C>;
const D: u32 = 32u;
const BQ: u32 = 32u;
const F: u32 = 16u;
const BK: u32 = 32u;
// Rows of f16 tiles padded by 8 halves (16 bytes), of f32 tiles by 4 floats: 16-byte strides
// whose rows start in different banks.
const PAD_H: u32 = 8u;
const PAD_F: u32 = 4u;

// @include attention_coop_backward_body.wgsl
