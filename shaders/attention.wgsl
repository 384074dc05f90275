// @variants D: 16 32 64 72
// Fused multi-head attention over variable-length segments, f32, flash style: the score
// matrix is never stored. Tensors are token-major: q [Nq, H, D], k and v [Nk, H, D],
// o [Nq, H, D], lse [Nq, H]. Queries of segment s (rows q_off[s] .. q_off[s+1]) attend only
// to keys k_off[s] .. k_off[s+1]; dense attention is the case of one segment.
//
// One workgroup handles one work item (a block of up to 32 rows of one segment, from the
// list built by `attention_blocks.wgsl`) for one head; each invocation owns one row, holding
// it and its accumulators in registers, while the workgroup stages tiles of 32 rows of the
// other side through workgroup memory.
//
// Forward (FlashAttention's online softmax): per query, a running maximum m and sum l of
// exp(score - m) in f32; each key tile rescales the accumulator once. lse = m + log l is saved
// for the backward pass, so exp(score - lse) recovers the probabilities exactly, and scores of
// any magnitude (1e4 and beyond) never overflow.
//
// Backward (FlashAttention-2): delta_i = dO_i . O_i; p_ij = exp(s_ij - lse_i);
// dV_j = sum_i p_ij dO_i; dS_ij = p_ij (dO_i . V_j - delta_i); dQ_i = scale sum_j dS_ij K_j;
// dK_j = scale sum_i dS_ij Q_i. `bwd_dq` walks keys for each query block, `bwd_dkv` walks
// queries for each key block: no atomics, and the result does not depend on scheduling.
// A query row without keys gets o = 0, lse = -inf and dq = 0.
//
// The forward and backward passes are `include/attention_forward.wgsl` and
// `include/attention_backward.wgsl`, shared with `attention_f16.wgsl`, which reads q, k and v
// as f16.

const D: u32 = 32u;
const D4: u32 = D / 4u;
const B: u32 = 32u; // rows per work item, and rows per staged tile

@group(0) @binding(0) var<storage, read> q: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> k: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> v: array<vec4<f32>>;

fn load_q(i: u32) -> vec4<f32> {
    return q[i];
}

fn load_k(i: u32) -> vec4<f32> {
    return k[i];
}

fn load_v(i: u32) -> vec4<f32> {
    return v[i];
}

// @include attention_forward.wgsl

// @include attention_backward.wgsl
