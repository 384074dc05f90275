// Sum, mean and max along one axis of a tensor viewed as [outer, len, inner].
// `rows` (inner == 1): one workgroup per row; each invocation folds a strided slice of the row,
// then a tree in workgroup memory. `strided` (inner > 1): one invocation per output, walking
// the axis; neighbouring invocations read neighbouring addresses, so the walk is coalesced.
// With `accumulate` the result is added to what y holds (a bias gradient summed into its
// parameter's gradient in the same pass).

struct Params {
    outer: u32,
    len: u32,
    inner: u32,
    op: u32, // 0 sum, 1 mean, 2 max
    accumulate: u32, // 1: y += result
}

@group(0) @binding(0) var<storage, read> x: array<f32>;
@group(0) @binding(1) var<storage, read_write> y: array<f32>;
var<immediate> pc: Params;

const REDUCE_OP_SUM: u32 = 0u;
const REDUCE_OP_MEAN: u32 = 1u;
const REDUCE_OP_MAX: u32 = 2u;

var<workgroup> partial: array<f32, 256>;

fn identity() -> f32 {
    if (pc.op == REDUCE_OP_MAX) {
        return bitcast<f32>(0xff800000u); // -inf, so a row of -inf has max -inf
    }
    return 0.0;
}

fn combine(a: f32, b: f32) -> f32 {
    if (pc.op == REDUCE_OP_MAX) {
        return max(a, b);
    }
    return a + b;
}

fn finish(v: f32) -> f32 {
    if (pc.op == REDUCE_OP_MEAN && pc.len > 0u) {
        return v / f32(pc.len);
    }
    return v;
}

fn store(o: u32, v: f32) {
    if (pc.accumulate != 0u) {
        y[o] += v;
    } else {
        y[o] = v;
    }
}

@compute @workgroup_size(256)
fn rows(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let row = wid.x + wid.y * nwg.x;
    // Uniform per workgroup: the whole group leaves together, before any barrier.
    if (row >= pc.outer) {
        return;
    }
    let base = row * pc.len;
    var acc = identity();
    for (var j = lid; j < pc.len; j += 256u) {
        acc = combine(acc, x[base + j]);
    }
    partial[lid] = acc;
    workgroupBarrier();
    for (var s = 128u; s > 0u; s >>= 1u) {
        if (lid < s) {
            partial[lid] = combine(partial[lid], partial[lid + s]);
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        store(row, finish(partial[0]));
    }
}

@compute @workgroup_size(256)
fn strided(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    let o = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (o >= pc.outer * pc.inner) {
        return;
    }
    let a = o / pc.inner;
    let c = o % pc.inner;
    let base = a * pc.len * pc.inner + c;
    if (pc.op == REDUCE_OP_MAX) {
        var m = identity();
        for (var j = 0u; j < pc.len; j++) {
            m = max(m, x[base + j * pc.inner]);
        }
        store(o, m);
        return;
    }
    // A serial walk along a long axis, summed in blocks of 64 whose sums are then added: the
    // rounding error grows with 64 + len / 64 instead of len. (Kahan compensation would be
    // simplified away by drivers that treat float arithmetic as reassociable.)
    var sum = 0.0;
    for (var j0 = 0u; j0 < pc.len; j0 += 64u) {
        var block = 0.0;
        let end = min(j0 + 64u, pc.len);
        for (var j = j0; j < end; j++) {
            block += x[base + j * pc.inner];
        }
        sum += block;
    }
    store(o, finish(sum));
}
