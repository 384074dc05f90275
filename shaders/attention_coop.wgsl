// @variants D: 16 32 64 72
// Fused segment attention, forward, on f16 q, k, v with cooperative matrices: 16x16x16
// fragments and subgroups of 32 (NVIDIA), 64 keys per tile. About 43 KiB of workgroup memory
// at D = 72. The kernel and its description: include/attention_coop_body.wgsl.

enable f16;
enable wgpu_cooperative_matrix;

alias FragA = coop_mat16x16<f16, A>;
alias FragB = coop_mat16x16<f16, B>;
alias FragC = coop_mat16x16<f32, C>;
const D: u32 = 32u;
const F: u32 = 16u;
const BK: u32 = 64u;
// Rows of f16 tiles padded by 8 halves (16 bytes), of f32 tiles by 4 floats: 16-byte strides
// whose rows start in different banks.
const PAD_H: u32 = 8u;
const PAD_F: u32 = 4u;

// @include attention_coop_body.wgsl
