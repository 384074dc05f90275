// Segment attention for CPU devices, forward and backward: the algorithm, layouts, bindings
// and outputs of `attention.wgsl` (see there), shaped for lavapipe, where every storage or
// workgroup-memory access is a loop over the SIMD group's lanes with a bounds check per lane
// and a barrier switches between a workgroup's SIMD groups (docs/decisions/kernels.md). The
// GPU kernels stage each tile of keys in workgroup memory and every invocation reads all of it
// back: 2 D / 4 vec4 loads per key for every row. Here a workgroup is one SIMD group of 8
// lanes with a row each (work items of B = 8 rows), with no workgroup memory and no barrier:
// per block of 8 keys (queries in `bwd_dkv`) each lane loads one key's rows of k and v, and
// the lanes take each key's values from the lane that loaded it by subgroup shuffles, so a
// key costs 2 D / 4 vec4 loads for all 8 rows together. Keys past the segment's end are read
// clamped to its last key and count for nothing (a score of -inf, a weight of 0).
//
// The including file defines D, D4, the bindings 0..2 of q, k and v and `load_q`, `load_k`,
// `load_v` (element i of its tensor, a vec4 of 4 consecutive features, as f32); B = 8 here.
// Taken where subgroups are exactly 8 lanes (engine/src/ops/attention.rs): the workgroup is
// then one SIMD group, every lane busy, and the shuffles stay within it.

// @include attention_common.wgsl

@group(0) @binding(6) var<storage, read_write> o: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> lse: array<f32>;
@group(0) @binding(8) var<storage, read> d_o: array<vec4<f32>>;
@group(0) @binding(9) var<storage, read_write> delta: array<f32>;
@group(0) @binding(10) var<storage, read_write> dq: array<vec4<f32>>;
@group(0) @binding(11) var<storage, read_write> dk: array<vec4<f32>>;
@group(0) @binding(12) var<storage, read_write> dv: array<vec4<f32>>;

const B: u32 = 8u;

// Lane j's x (j < 8, the same on every lane). A shuffle with a uniform lane index: on
// lavapipe half the time of a broadcast from a constant lane picked by a switch over j, and
// quicker to compile (docs/decisions/kernels.md).
fn lane_v(x: vec4<f32>, j: u32) -> vec4<f32> {
    return subgroupShuffle(x, j);
}

fn lane_s(x: f32, j: u32) -> f32 {
    return subgroupShuffle(x, j);
}

@compute @workgroup_size(8)
fn fwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
       @builtin(local_invocation_index) lid: u32) {
    let item = work_item(wid, nwg);
    if (item.x == 0xffffffffu) {
        return;
    }
    let h = item.z;
    let row = item.y + lid;
    let rows = segment_rows(item.x, false);
    let live = row < rows.x;
    let k_begin = rows.y;
    let k_end = rows.z;

    var qr: array<vec4<f32>, D4>;
    var acc: array<vec4<f32>, D4>;
    for (var c = 0u; c < D4; c++) {
        acc[c] = vec4<f32>(0.0);
        qr[c] = vec4<f32>(0.0);
        if (live) {
            qr[c] = load_q((row * pc.heads + h) * D4 + c) * pc.scale;
        }
    }
    var m = neg_inf();
    var l = 0.0;
    var kr: array<vec4<f32>, D4>;
    var vr: array<vec4<f32>, D4>;
    var s: array<f32, B>;
    for (var kt = k_begin; kt < k_end; kt += B) {
        let count = min(B, k_end - kt);
        let key = min(kt + lid, k_end - 1u);
        for (var c = 0u; c < D4; c++) {
            let at = (key * pc.heads + h) * D4 + c;
            kr[c] = load_k(at);
            vr[c] = load_v(at);
        }
        var block_max = neg_inf();
        for (var j = 0u; j < B; j++) {
            var d = 0.0;
            for (var c = 0u; c < D4; c++) {
                d += dot(qr[c], lane_v(kr[c], j));
            }
            s[j] = select(neg_inf(), d, j < count);
            block_max = max(block_max, s[j]);
        }
        let m_new = max(m, block_max);
        let correction = exp(m - m_new);
        l *= correction;
        for (var c = 0u; c < D4; c++) {
            acc[c] *= correction;
        }
        for (var j = 0u; j < B; j++) {
            let p = exp(s[j] - m_new);
            l += p;
            for (var c = 0u; c < D4; c++) {
                acc[c] += p * lane_v(vr[c], j);
            }
        }
        m = m_new;
    }
    if (live) {
        var inv = 0.0;
        var row_lse = neg_inf();
        if (l > 0.0) {
            inv = 1.0 / l;
            row_lse = m + log(l);
        }
        for (var c = 0u; c < D4; c++) {
            o[(row * pc.heads + h) * D4 + c] = acc[c] * inv;
        }
        lse[row * pc.heads + h] = row_lse;
    }
}

@compute @workgroup_size(8)
fn bwd_dq(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
          @builtin(local_invocation_index) lid: u32) {
    let item = work_item(wid, nwg);
    if (item.x == 0xffffffffu) {
        return;
    }
    let h = item.z;
    let row = item.y + lid;
    let rows = segment_rows(item.x, false);
    let live = row < rows.x;
    let k_begin = rows.y;
    let k_end = rows.z;

    var qr: array<vec4<f32>, D4>;
    var gr: array<vec4<f32>, D4>; // dO row
    var acc: array<vec4<f32>, D4>; // dQ row
    var row_delta = 0.0;
    var row_lse = 0.0;
    for (var c = 0u; c < D4; c++) {
        acc[c] = vec4<f32>(0.0);
        qr[c] = vec4<f32>(0.0);
        gr[c] = vec4<f32>(0.0);
        if (live) {
            let at = (row * pc.heads + h) * D4 + c;
            qr[c] = load_q(at) * pc.scale;
            gr[c] = d_o[at];
            row_delta += dot(gr[c], o[at]);
        }
    }
    if (live) {
        row_lse = lse[row * pc.heads + h];
        // bwd_dkv reads delta after this kernel (the recorder puts a barrier between them).
        delta[row * pc.heads + h] = row_delta;
    }
    var kr: array<vec4<f32>, D4>;
    var vr: array<vec4<f32>, D4>;
    var kj: array<vec4<f32>, D4>;
    for (var kt = k_begin; kt < k_end; kt += B) {
        let count = min(B, k_end - kt);
        let key = min(kt + lid, k_end - 1u);
        for (var c = 0u; c < D4; c++) {
            let at = (key * pc.heads + h) * D4 + c;
            kr[c] = load_k(at);
            vr[c] = load_v(at);
        }
        for (var j = 0u; j < B; j++) {
            var sc = 0.0;
            var dp = 0.0;
            for (var c = 0u; c < D4; c++) {
                kj[c] = lane_v(kr[c], j);
                sc += dot(qr[c], kj[c]);
                dp += dot(gr[c], lane_v(vr[c], j));
            }
            let ds = select(0.0, exp(sc - row_lse) * (dp - row_delta), j < count);
            for (var c = 0u; c < D4; c++) {
                acc[c] += ds * kj[c];
            }
        }
    }
    if (live) {
        for (var c = 0u; c < D4; c++) {
            dq[(row * pc.heads + h) * D4 + c] = acc[c] * pc.scale;
        }
    }
}

@compute @workgroup_size(8)
fn bwd_dkv(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    // Work items here are blocks of keys; each lane loads a query of the block of 8.
    let item = work_item(wid, nwg);
    if (item.x == 0xffffffffu) {
        return;
    }
    let h = item.z;
    let row = item.y + lid;
    let rows = segment_rows(item.x, true);
    let live = row < rows.x;
    let q_begin = rows.y;
    let q_end = rows.z;

    var kr: array<vec4<f32>, D4>;
    var vr: array<vec4<f32>, D4>;
    var gk: array<vec4<f32>, D4>;
    var gv: array<vec4<f32>, D4>;
    for (var c = 0u; c < D4; c++) {
        gk[c] = vec4<f32>(0.0);
        gv[c] = vec4<f32>(0.0);
        kr[c] = vec4<f32>(0.0);
        vr[c] = vec4<f32>(0.0);
        if (live) {
            let at = (row * pc.heads + h) * D4 + c;
            kr[c] = load_k(at) * pc.scale;
            vr[c] = load_v(at);
        }
    }
    var qr: array<vec4<f32>, D4>;
    var gr: array<vec4<f32>, D4>;
    var qi: array<vec4<f32>, D4>;
    var gi: array<vec4<f32>, D4>;
    for (var qt = q_begin; qt < q_end; qt += B) {
        let count = min(B, q_end - qt);
        let query = min(qt + lid, q_end - 1u);
        for (var c = 0u; c < D4; c++) {
            let at = (query * pc.heads + h) * D4 + c;
            qr[c] = load_q(at);
            gr[c] = d_o[at];
        }
        let query_lse = lse[query * pc.heads + h];
        let query_delta = delta[query * pc.heads + h];
        for (var i = 0u; i < B; i++) {
            var sc = 0.0;
            var dp = 0.0;
            for (var c = 0u; c < D4; c++) {
                qi[c] = lane_v(qr[c], i);
                gi[c] = lane_v(gr[c], i);
                sc += dot(kr[c], qi[c]);
                dp += dot(vr[c], gi[c]);
            }
            let p = select(0.0, exp(sc - lane_s(query_lse, i)), i < count);
            let ds = p * (dp - lane_s(query_delta, i));
            for (var c = 0u; c < D4; c++) {
                gv[c] += p * gi[c];
                gk[c] += ds * qi[c];
            }
        }
    }
    if (live) {
        for (var c = 0u; c < D4; c++) {
            let at = (row * pc.heads + h) * D4 + c;
            dk[at] = gk[c] * pc.scale;
            dv[at] = gv[c];
        }
    }
}
