// Global L2 norm of a flat f32 buffer in two stages.
// `sumsq_partial`: `groups` workgroups walk the buffer with a grid stride, each invocation
// summing squares of its elements, then a tree in workgroup memory; each workgroup writes one
// partial sum at partials[partial_base + group]. A buffer larger than one binding is reduced
// chunk by chunk into consecutive runs of partials.
// `finish`: one workgroup adds the first `count` partials and writes sqrt(sum) to out[0] and
// the sum itself to out[1]. NaN or Inf anywhere in the input makes the norm non-finite.

struct Params {
    n: u32,            // elements of this chunk
    groups: u32,       // workgroups of this chunk's dispatch
    partial_base: u32, // where this chunk's partials start
    count: u32,        // finish: number of partials
}

@group(0) @binding(0) var<storage, read> x: array<f32>;
@group(0) @binding(1) var<storage, read_write> partials: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;
var<immediate> pc: Params;

var<workgroup> acc: array<f32, 256>;

fn tree_sum(lid: u32, s: f32) -> f32 {
    acc[lid] = s;
    workgroupBarrier();
    for (var k = 128u; k > 0u; k >>= 1u) {
        if (lid < k) {
            acc[lid] += acc[lid + k];
        }
        workgroupBarrier();
    }
    return acc[0];
}

@compute @workgroup_size(256)
fn sumsq_partial(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32) {
    let group = wid.x + wid.y * nwg.x;
    // Uniform per workgroup: the whole group leaves together, before any barrier.
    if (group >= pc.groups) {
        return;
    }
    let stride = pc.groups * 256u;
    var s = 0.0;
    for (var i = group * 256u + lid; i < pc.n; i += stride) {
        let e = x[i];
        s += e * e;
    }
    let total = tree_sum(lid, s);
    if (lid == 0u) {
        partials[pc.partial_base + group] = total;
    }
}

@compute @workgroup_size(256)
fn finish(@builtin(local_invocation_index) lid: u32) {
    var s = 0.0;
    for (var j = lid; j < pc.count; j += 256u) {
        s += partials[j];
    }
    let total = tree_sum(lid, s);
    if (lid == 0u) {
        out[0] = sqrt(total);
        out[1] = total;
    }
}
