// What every segment-attention kernel shares: the push constants, the segment offsets and work
// list (bindings 3..5), and how a workgroup finds its work item and its segment's rows. Included
// by `attention_forward.wgsl` (and so `attention.wgsl`, `attention_f16.wgsl`) and by
// `attention_coop_body.wgsl`.

struct Params {
    heads: u32,
    items: u32, // work-list entries x heads: the workgroups that have work
    scale: f32,
    nq: u32,    // rows of q; offsets are clamped to it, so bad offsets cannot read past it
    nk: u32,    // rows of k and v
}

@group(0) @binding(3) var<storage, read> q_off: array<u32>;
@group(0) @binding(4) var<storage, read> k_off: array<u32>;
@group(0) @binding(5) var<storage, read> work: array<vec2<u32>>;
var<immediate> pc: Params;

fn neg_inf() -> f32 {
    return bitcast<f32>(0xff800000u);
}

// The work item of this workgroup: (segment, first row, head), or segment 0xffffffff.
fn work_item(wid: vec3<u32>, nwg: vec3<u32>) -> vec3<u32> {
    let id = wid.x + wid.y * nwg.x;
    if (id >= pc.items) {
        return vec3<u32>(0xffffffffu, 0u, 0u);
    }
    let w = work[id / pc.heads];
    return vec3<u32>(w.x, w.y, id % pc.heads);
}

// The rows of segment `seg` on each side, clamped to the tensors (so bad offsets cannot reach
// past them): (own end, other begin, other end). The block's own side is the queries' in
// `fwd` and `bwd_dq`, the keys' in `bwd_dkv` (`keys_own`). Nothing here depends on the
// invocation, so loops bounded by it stay uniform for their barriers.
fn segment_rows(seg: u32, keys_own: bool) -> vec3<u32> {
    if keys_own {
        let begin = min(q_off[seg], pc.nq);
        return vec3<u32>(min(k_off[seg + 1u], pc.nk), begin, clamp(q_off[seg + 1u], begin, pc.nq));
    }
    let begin = min(k_off[seg], pc.nk);
    return vec3<u32>(min(q_off[seg + 1u], pc.nq), begin, clamp(k_off[seg + 1u], begin, pc.nk));
}
