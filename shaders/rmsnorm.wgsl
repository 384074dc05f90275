// RMSNorm over the last axis: y = x * rstd * w, rstd = 1 / sqrt(mean(x^2) + eps).
// `forward` and `backward` take one row per workgroup and reduce in workgroup memory (the
// pattern of softmax.wgsl). `param_grads` gives each invocation one column and a chunk of rows
// and writes partial sums of dw = sum_rows dy * x * rstd, which the host reduces over chunks.
//
// Backward (xhat = x * rstd, g = dy * w):  dx = rstd * (g - xhat * mean(g * xhat)).

struct Params {
    rows: u32,
    width: u32,
    eps: f32,
    rows_per_chunk: u32,
}

@group(0) @binding(0) var<storage, read> x: array<f32>;
@group(0) @binding(1) var<storage, read> w: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;
@group(0) @binding(3) var<storage, read_write> rstd: array<f32>;
@group(0) @binding(4) var<storage, read> dy: array<f32>;
@group(0) @binding(5) var<storage, read_write> dx: array<f32>;
@group(0) @binding(6) var<storage, read_write> dw_part: array<f32>;
var<immediate> pc: Params;

// @include row_reduce.wgsl

@compute @workgroup_size(256)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let row = wid.x + wid.y * nwg.x;
    if (row >= pc.rows) {
        return;
    }
    let base = row * pc.width;
    var ss = 0.0;
    for (var j = lid; j < pc.width; j += 256u) {
        let v = x[base + j];
        ss += v * v;
    }
    ss = reduce_sum(lid, ss);
    let r = inverseSqrt(ss / f32(pc.width) + pc.eps);
    for (var j = lid; j < pc.width; j += 256u) {
        y[base + j] = x[base + j] * r * w[j];
    }
    if (lid == 0u) {
        rstd[row] = r;
    }
}

@compute @workgroup_size(256)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let row = wid.x + wid.y * nwg.x;
    if (row >= pc.rows) {
        return;
    }
    let base = row * pc.width;
    let r = rstd[row];
    var dot = 0.0;
    for (var j = lid; j < pc.width; j += 256u) {
        dot += dy[base + j] * w[j] * x[base + j] * r;
    }
    let m = reduce_sum(lid, dot) / f32(pc.width);
    for (var j = lid; j < pc.width; j += 256u) {
        let xhat = x[base + j] * r;
        dx[base + j] = r * (dy[base + j] * w[j] - xhat * m);
    }
}

@compute @workgroup_size(64)
fn param_grads(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let col = wid.x * 64u + lid;
    if (col >= pc.width) {
        return;
    }
    let chunk = wid.y;
    let start = chunk * pc.rows_per_chunk;
    let end = min(start + pc.rows_per_chunk, pc.rows);
    var acc = 0.0;
    for (var r = start; r < end; r++) {
        let i = r * pc.width + col;
        acc += dy[i] * x[i] * rstd[r];
    }
    dw_part[chunk * pc.width + col] = acc;
}
