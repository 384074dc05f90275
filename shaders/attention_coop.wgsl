// @variants D: 16 32 64 72
// @variants BQ: 32 128
// @variants BK: 32 64
// Fused segment attention, forward, on f16 q, k, v with cooperative matrices: 16x16x16
// fragments and subgroups of 32 (NVIDIA), tiles of 32 or 64 keys, blocks of 32 or 128 query
// rows (one subgroup per 16). Workgroup memory with 32-key tiles at BQ = 128: 38 KiB at
// D = 32, 46 KiB at D = 64; 50 KiB at D = 72, over the 48 KiB NVIDIA offers, so D = 72 runs
// blocks of 32. 64-key tiles take 52 KiB at BQ = 128 before any key (the scores and weights
// of 8 subgroups), so on 48 KiB they run in blocks of 32 at D = 16 and 32 (33 KiB at D = 32);
// a device with more workgroup memory takes them in tall blocks too. The kernel and its
// description: include/attention_coop_body.wgsl.

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

// @include attention_coop_body.wgsl
