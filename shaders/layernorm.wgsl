// @variants WG: 256 8
// LayerNorm over the last axis: xhat = (x - mean) * rstd, rstd = 1 / sqrt(var + eps),
// y = xhat * w + b when `affine`, else y = xhat (w and b are then not read; the host binds x in
// their place). The variance is a second pass over (x - mean)^2, never E[x^2] - mean^2, so rows
// around 1e4 keep their precision; eps keeps constant rows (variance 0) finite.
// `forward` and `backward` give each row `pc.lanes` invocations (row_reduce.wgsl);
// `param_grads` gives each invocation one column and a chunk of rows and writes partial sums of
// dw = sum_rows dy * xhat and db = sum_rows dy, which the host reduces over chunks.
//
// Backward (g = dy * w):  dx = rstd * (g - mean(g) - xhat * mean(g * xhat)).

struct Params {
    rows: u32,
    width: u32,
    eps: f32,
    rows_per_chunk: u32,
    affine: u32,
    lanes: u32,
    residual: u32, // backward: add `res` into dx
    _pad: u32,
}

@group(0) @binding(0) var<storage, read> x: array<f32>;
@group(0) @binding(1) var<storage, read> w: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> y: array<f32>;
@group(0) @binding(4) var<storage, read_write> mean: array<f32>;
@group(0) @binding(5) var<storage, read_write> rstd: array<f32>;
@group(0) @binding(6) var<storage, read> dy: array<f32>;
@group(0) @binding(7) var<storage, read_write> dx: array<f32>;
@group(0) @binding(8) var<storage, read_write> dw_part: array<f32>;
@group(0) @binding(9) var<storage, read_write> db_part: array<f32>;
@group(0) @binding(10) var<storage, read> res: array<f32>;
var<immediate> pc: Params;

// @include row_reduce.wgsl

var<workgroup> partial2: array<f32, WG>;

// Two sums at once (one set of barriers).
fn reduce_sum2(lid: u32, lanes: u32, v: vec2<f32>) -> vec2<f32> {
    if (lanes == 1u) {
        return v;
    }
    partial[lid] = v.x;
    partial2[lid] = v.y;
    workgroupBarrier();
    for (var s = lanes / 2u; s > 0u; s >>= 1u) {
        if ((lid & (lanes - 1u)) < s) {
            partial[lid] = partial[lid] + partial[lid + s];
            partial2[lid] = partial2[lid] + partial2[lid + s];
        }
        workgroupBarrier();
    }
    let first = lid & ~(lanes - 1u);
    let r = vec2<f32>(partial[first], partial2[first]);
    workgroupBarrier();
    return r;
}

@compute @workgroup_size(WG)
fn forward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let at = row_slot(wid, nwg, lid, pc.lanes, pc.rows);
    if (at.first_row >= pc.rows) {
        return;
    }
    let row = at.row;
    let base = row * pc.width;
    let end = select(0u, pc.width, at.live);
    let n = f32(pc.width);
    var s = 0.0;
    for (var j = at.lane; j < end; j += pc.lanes) {
        s += x[base + j];
    }
    let mu = reduce_sum(lid, pc.lanes, s) / n;
    var ss = 0.0;
    for (var j = at.lane; j < end; j += pc.lanes) {
        let d = x[base + j] - mu;
        ss += d * d;
    }
    let r = inverseSqrt(reduce_sum(lid, pc.lanes, ss) / n + pc.eps);
    for (var j = at.lane; j < end; j += pc.lanes) {
        let xhat = (x[base + j] - mu) * r;
        if (pc.affine != 0u) {
            y[base + j] = xhat * w[j] + b[j];
        } else {
            y[base + j] = xhat;
        }
    }
    if (at.live && at.lane == 0u) {
        mean[row] = mu;
        rstd[row] = r;
    }
}

@compute @workgroup_size(WG)
fn backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
            @builtin(local_invocation_index) lid: u32) {
    let at = row_slot(wid, nwg, lid, pc.lanes, pc.rows);
    if (at.first_row >= pc.rows) {
        return;
    }
    let base = at.row * pc.width;
    let end = select(0u, pc.width, at.live);
    let safe = min(at.row, pc.rows - 1u);
    let mu = mean[safe];
    let r = rstd[safe];
    var acc = vec2<f32>(0.0, 0.0);
    for (var j = at.lane; j < end; j += pc.lanes) {
        var g = dy[base + j];
        if (pc.affine != 0u) {
            g *= w[j];
        }
        acc += vec2<f32>(g, g * (x[base + j] - mu) * r);
    }
    let m = reduce_sum2(lid, pc.lanes, acc) / f32(pc.width);
    for (var j = at.lane; j < end; j += pc.lanes) {
        var g = dy[base + j];
        if (pc.affine != 0u) {
            g *= w[j];
        }
        let xhat = (x[base + j] - mu) * r;
        var v = r * (g - m.x - xhat * m.y);
        if (pc.residual != 0u) {
            v += res[base + j];
        }
        dx[base + j] = v;
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
    var dw_acc = 0.0;
    var db_acc = 0.0;
    for (var r = start; r < end; r++) {
        let i = r * pc.width + col;
        dw_acc += dy[i] * (x[i] - mean[r]) * rstd[r];
        db_acc += dy[i];
    }
    dw_part[chunk * pc.width + col] = dw_acc;
    db_part[chunk * pc.width + col] = db_acc;
}
