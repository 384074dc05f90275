// The backward pass of segment attention (see `attention.wgsl` for the algorithm), included
// by `attention.wgsl` (f32 q, k, v) and `attention_f16.wgsl` (f16 q, k, v), which define B, D,
// D4, the bindings q, k, v and their loads `load_q/k/v` (widening to f32). Everything else is
// f32: o, lse and dO in, dq, dk and dv out.
@group(0) @binding(8) var<storage, read> d_o: array<vec4<f32>>;
@group(0) @binding(9) var<storage, read_write> delta: array<f32>;
@group(0) @binding(10) var<storage, read_write> dq: array<vec4<f32>>;
@group(0) @binding(11) var<storage, read_write> dk: array<vec4<f32>>;
@group(0) @binding(12) var<storage, read_write> dv: array<vec4<f32>>;

@compute @workgroup_size(32)
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
    for (var kt = k_begin; kt < k_end; kt += B) {
        let count = min(B, k_end - kt);
        workgroupBarrier();
        stage_k(kt, count, h, lid);
        workgroupBarrier();
        if (live) {
            for (var j = 0u; j < B; j++) {
                if (j < count) {
                    var sc = 0.0;
                    var dp = 0.0;
                    for (var c = 0u; c < D4; c++) {
                        sc += dot(qr[c], tile_a[j * D4 + c]);
                        dp += dot(gr[c], tile_b[j * D4 + c]);
                    }
                    let ds = exp(sc - row_lse) * (dp - row_delta);
                    for (var c = 0u; c < D4; c++) {
                        acc[c] += ds * tile_a[j * D4 + c];
                    }
                }
            }
        }
    }
    if (live) {
        for (var c = 0u; c < D4; c++) {
            dq[(row * pc.heads + h) * D4 + c] = acc[c] * pc.scale;
        }
    }
}

@compute @workgroup_size(32)
fn bwd_dkv(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    // Work items here are blocks of keys.
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
    for (var qt = q_begin; qt < q_end; qt += B) {
        let count = min(B, q_end - qt);
        workgroupBarrier();
        for (var i = lid; i < B * D4; i += B) {
            let r = i / D4;
            if (r < count) {
                let src = ((qt + r) * pc.heads + h) * D4 + (i % D4);
                tile_a[i] = load_q(src);
                tile_b[i] = d_o[src];
            }
        }
        if (lid < count) {
            tile_lse[lid] = lse[(qt + lid) * pc.heads + h];
            tile_delta[lid] = delta[(qt + lid) * pc.heads + h];
        }
        workgroupBarrier();
        if (live) {
            for (var i = 0u; i < B; i++) {
                if (i < count) {
                    var sc = 0.0;
                    var dp = 0.0;
                    for (var c = 0u; c < D4; c++) {
                        sc += dot(kr[c], tile_a[i * D4 + c]);
                        dp += dot(vr[c], tile_b[i * D4 + c]);
                    }
                    let p = exp(sc - tile_lse[i]);
                    let ds = p * (dp - tile_delta[i]);
                    for (var c = 0u; c < D4; c++) {
                        gv[c] += p * tile_b[i * D4 + c];
                        gk[c] += ds * tile_a[i * D4 + c];
                    }
                }
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
