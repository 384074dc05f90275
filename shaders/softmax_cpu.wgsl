// Row softmax for CPU devices (lavapipe), rows of a multiple of 4: a row per invocation in
// workgroups of 8 (one SIMD group), read and written as vec4s (lavapipe runs every storage
// access as a loop over the lanes, so four values an access cost half as much per value as one),
// in two passes: the running maximum and the sum of exp(x - max) together (the sum rescaled
// when the maximum grows, as in the streaming softmax of FlashAttention), then the normalised
// output. The same push constants as softmax.wgsl; host side engine/src/ops/softmax.rs.

struct Params {
    rows: u32,
    len: u32,
    lanes: u32,
}

@group(0) @binding(0) var<storage, read> x: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read_write> y: array<vec4<f32>>;
var<immediate> pc: Params;

@compute @workgroup_size(8)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let row = (wid.x + wid.y * nwg.x) * 8u + lid;
    if (row >= pc.rows) {
        return;
    }
    let len4 = pc.len / 4u;
    let base = row * len4;
    // Per component: the maximum so far and the sum of exp(x - maximum), summed in blocks of
    // 64 (`t`) added to the total (`s`), so that rows of 10^5 keep the accuracy of a tree: a
    // plain running sum loses 1e-5 of it there (relative), the blocks 1e-6.
    var m = vec4<f32>(bitcast<f32>(0xff800000u)); // -inf
    var s = vec4<f32>(0.0);
    for (var start = 0u; start < len4; start += 64u) {
        var t = vec4<f32>(0.0);
        for (var j = start; j < min(start + 64u, len4); j++) {
            let v = x[base + j];
            let grown = max(m, v);
            // exp(-inf - -inf) would be NaN: a component still at -inf has nothing to rescale.
            let f = select(exp(m - grown), vec4<f32>(1.0), m == grown);
            t = t * f + exp(v - grown);
            s *= f;
            m = grown;
        }
        s += t;
    }
    let row_max = max(max(m.x, m.y), max(m.z, m.w));
    let sum = dot(s, exp(m - vec4<f32>(row_max)));
    let inv = 1.0 / sum;
    for (var j = 0u; j < len4; j++) {
        y[base + j] = exp(x[base + j] - vec4<f32>(row_max)) * inv;
    }
}
