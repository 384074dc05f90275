// Row softmax for CPU devices (lavapipe), rows of a multiple of 4: a row per invocation in
// workgroups of 8 (one SIMD group), read through a texel buffer as vec4s (a branch-free gather
// on lavapipe, where a storage-buffer read is a loop over the lanes) and written as vec4s, in
// two passes: the running maximum with the sum of exp(x - max) (the sum rescaled when the
// maximum grows, as in the streaming softmax of FlashAttention), 4 vec4s a step so that the
// rescaling costs one exp per 16 values, then the normalised output. The same push constants as
// softmax.wgsl; host side engine/src/ops/softmax.rs. On lavapipe 25, one thread, 256 x 1024:
// 0.44 ms against 0.65 with storage-buffer reads and a rescaling a vec4 (docs/decisions/kernels.md).

struct Params {
    rows: u32,
    len: u32,
    lanes: u32,
}

// A texel buffer of vec4s (engine/build.rs).
@group(0) @binding(0) var x: texture_storage_1d<rgba32float, read>;
@group(0) @binding(1) var<storage, read_write> y: array<vec4<f32>>;
var<immediate> pc: Params;

// The running maximum `m` and the sums `t` (this block of 64 vec4s) and `s` (the blocks before)
// of exp(x - m), per component.
struct Running {
    m: vec4<f32>,
    t: vec4<f32>,
    s: vec4<f32>,
}

// `r` with the values of `v` taken in, whose maximum with r.m is `grown`.
fn take(r: Running, grown: vec4<f32>) -> Running {
    // exp(-inf - -inf) would be NaN: a component still at -inf has nothing to rescale.
    let f = select(exp(r.m - grown), vec4<f32>(1.0), r.m == grown);
    return Running(grown, r.t * f, r.s * f);
}

@compute @workgroup_size(8)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let row = (wid.x + wid.y * nwg.x) * 8u + lid;
    if (row >= pc.rows) {
        return;
    }
    let len4 = pc.len / 4u;
    let base = row * len4;
    // Summed in blocks of 64 vec4s (`t`) added to the total (`s`), so that rows of 10^5 keep the
    // accuracy of a tree: a plain running sum loses 1e-5 of it there (relative), the blocks 1e-6.
    var r = Running(vec4<f32>(bitcast<f32>(0xff800000u)), vec4<f32>(0.0), vec4<f32>(0.0)); // m = -inf
    let whole = len4 & ~3u;
    for (var start = 0u; start < len4; start += 64u) {
        let end = min(start + 64u, len4);
        var j = start;
        // 4 vec4s a step: one rescaling for all of them.
        for (; j + 4u <= min(end, whole); j += 4u) {
            let v0 = textureLoad(x, base + j);
            let v1 = textureLoad(x, base + j + 1u);
            let v2 = textureLoad(x, base + j + 2u);
            let v3 = textureLoad(x, base + j + 3u);
            let grown = max(max(max(r.m, v0), max(v1, v2)), v3);
            r = take(r, grown);
            r.t += exp(v0 - grown) + exp(v1 - grown) + exp(v2 - grown) + exp(v3 - grown);
        }
        for (; j < end; j++) {
            let v = textureLoad(x, base + j);
            let grown = max(r.m, v);
            r = take(r, grown);
            r.t += exp(v - grown);
        }
        r.s += r.t;
        r.t = vec4<f32>(0.0);
    }
    let row_max = max(max(r.m.x, r.m.y), max(r.m.z, r.m.w));
    let sum = dot(r.s, exp(r.m - vec4<f32>(row_max)));
    let inv = 1.0 / sum;
    for (var j = 0u; j < len4; j++) {
        y[base + j] = exp(textureLoad(x, base + j) - vec4<f32>(row_max)) * inv;
    }
}
