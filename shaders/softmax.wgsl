// Row softmax: one workgroup per row of any length. Three passes over the row: the maximum,
// the sum of exp(x - max) (both reduced in workgroup memory), then the normalised output.
// Subtracting the row maximum keeps every exponent <= 0, so rows with scores of 1e4 or more
// neither overflow nor lose the largest entries.

struct Params {
    rows: u32,
    len: u32,
}

@group(0) @binding(0) var<storage, read> x: array<f32>;
@group(0) @binding(1) var<storage, read_write> y: array<f32>;
var<immediate> pc: Params;

// @include row_reduce.wgsl

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let row = wid.x + wid.y * nwg.x;
    if (row >= pc.rows) {
        return;
    }
    let base = row * pc.len;
    var m = bitcast<f32>(0xff800000u); // -inf
    for (var j = lid; j < pc.len; j += 256u) {
        m = max(m, x[base + j]);
    }
    m = reduce_max(lid, m);
    var s = 0.0;
    for (var j = lid; j < pc.len; j += 256u) {
        s += exp(x[base + j] - m);
    }
    s = reduce_sum(lid, s);
    let inv = 1.0 / s;
    for (var j = lid; j < pc.len; j += 256u) {
        y[base + j] = exp(x[base + j] - m) * inv;
    }
}
