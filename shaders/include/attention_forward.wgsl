// The forward pass of fused segment attention, shared by `attention.wgsl` (f32 q, k, v) and
// `attention_f16.wgsl` (f16 q, k, v): the including file defines D, D4 and B, the bindings
// 0..2 of q, k and v, and `load_q`, `load_k`, `load_v`, which return element i of its
// tensor (a vec4 of 4 consecutive features) as f32. Everything after the load is f32.

// @include attention_common.wgsl

@group(0) @binding(6) var<storage, read_write> o: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> lse: array<f32>;

// Staged tiles: keys and values (forward, dq), or queries, output gradients, lse and delta
// (dk, dv).
var<workgroup> tile_a: array<vec4<f32>, B * D4>;
var<workgroup> tile_b: array<vec4<f32>, B * D4>;
var<workgroup> tile_lse: array<f32, B>;
var<workgroup> tile_delta: array<f32, B>;

// Stages rows first .. first + count of a [rows, H, D] tensor, head h, into a tile.
fn stage_k(first: u32, count: u32, h: u32, lid: u32) {
    for (var i = lid; i < B * D4; i += B) {
        let r = i / D4;
        if (r < count) {
            let src = ((first + r) * pc.heads + h) * D4 + (i % D4);
            tile_a[i] = load_k(src);
            tile_b[i] = load_v(src);
        }
    }
}

@compute @workgroup_size(32)
fn fwd(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
       @builtin(local_invocation_index) lid: u32) {
    let item = work_item(wid, nwg);
    // Uniform across the workgroup: unused list entries leave together, before any barrier.
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
    var s: array<f32, B>;
    for (var kt = k_begin; kt < k_end; kt += B) {
        let count = min(B, k_end - kt);
        workgroupBarrier(); // the previous tile is consumed
        stage_k(kt, count, h, lid);
        workgroupBarrier();
        if (live) {
            var tile_max = neg_inf();
            for (var j = 0u; j < B; j++) {
                if (j < count) {
                    var d = 0.0;
                    for (var c = 0u; c < D4; c++) {
                        d += dot(qr[c], tile_a[j * D4 + c]);
                    }
                    s[j] = d;
                    tile_max = max(tile_max, d);
                }
            }
            let m_new = max(m, tile_max);
            let correction = exp(m - m_new);
            l *= correction;
            for (var c = 0u; c < D4; c++) {
                acc[c] *= correction;
            }
            for (var j = 0u; j < B; j++) {
                if (j < count) {
                    let p = exp(s[j] - m_new);
                    l += p;
                    for (var c = 0u; c < D4; c++) {
                        acc[c] += p * tile_b[j * D4 + c];
                    }
                }
            }
            m = m_new;
        }
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
