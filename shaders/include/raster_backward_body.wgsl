// The blend backward kernel, shared by `raster_backward.wgsl` (per-pair sums, deterministic),
// `raster_backward_atomic.wgsl` (native f32 atomic add) and `raster_backward_cas.wgsl`
// (compare-and-swap), which each define the `grads` binding and four functions:
// `init_grads(lid)`, called by every invocation first; `chunk_size(nsg)`, the Gaussians between
// flushes for `nsg` subgroups a workgroup; `store_grad(sg, nsg, lane, j, gaussian, c, sum)`,
// called by every invocation of a subgroup that touched the j-th Gaussian of a chunk, with the
// subgroup's sum of channel c (one channel a call: an array passed by value reads stale memory
// on lavapipe, see engine/build.rs); and `flush_grads(lid, chunk, nsg, entry)`, called by every invocation after
// each chunk (in uniform control flow, so it may hold barriers), where `entry` is the place of
// the chunk's first Gaussian in the sorted tile list (the j-th is at `entry - j`).
//
// One workgroup per tile, one invocation per pixel, walking the tile's Gaussians back to front
// from the last one any pixel blended, in batches staged through workgroup memory. Each pixel
// starts from its final transmittance T and, for each Gaussian it blended (entries before its
// `last`, alpha >= min_alpha), recovers T_i = T_(i+1) / (1 - alpha_i). With five channels
// f = (r, g, b, depth, 1) and background (bg, 0, 0), the colour behind Gaussian i seen from
// just after it is R_i (R = bg at the end, R_(i-1) = f_i alpha_i + R_i (1 - alpha_i)), and
// dL/dalpha_i = T_i sum_k g_k (f_ik - R_ik), dL/df_i = g alpha_i T_i. Alpha clamped at
// alpha_max passes no gradient to the opacity or the footprint.
//
// The ten per-Gaussian sums (du, dv, conic a b c, opacity, rgb, depth) are reduced over the
// subgroup with subgroupAdd first: the batch loop is uniform over the workgroup, and pixels
// that do not touch a Gaussian add zeros. Nothing depends on the subgroup size.

// @include raster_blend_params.wgsl

@group(0) @binding(0) var<storage, read> ranges: array<u32>;
@group(0) @binding(1) var<storage, read> ids: array<u32>;
@group(0) @binding(2) var<storage, read> proj: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> final_t: array<f32>;
@group(0) @binding(4) var<storage, read> last_in: array<u32>;
@group(0) @binding(5) var<storage, read> d_rgb: array<f32>;
@group(0) @binding(6) var<storage, read> d_alpha: array<f32>;
@group(0) @binding(7) var<storage, read> d_depth: array<f32>;
var<immediate> pc: Params;

const BATCH: u32 = 256u;

var<workgroup> s_id: array<u32, BATCH>;
var<workgroup> s_xy_op: array<vec4<f32>, BATCH>;
var<workgroup> s_conic: array<vec4<f32>, BATCH>;
var<workgroup> s_colour: array<vec4<f32>, BATCH>;
var<workgroup> max_last: atomic<u32>;
var<workgroup> max_last_plain: u32;
var<workgroup> chunk_plain: u32;

// One-dimensional (subgroup builtins need it): pixel (lid % 16, lid / 16) of the tile.
@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32,
        @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_id) sg: u32,
        @builtin(num_subgroups) nsg: u32) {
    let tile = wid.y * pc.tiles_x + wid.x;
    let px = wid.x * 16u + (lid & 15u);
    let py = wid.y * 16u + (lid >> 4u);
    let inside = px < pc.width && py < pc.height;
    let pix = vec2<f32>(f32(px) + 0.5, f32(py) + 0.5);
    let start = ranges[2u * tile];

    var t = 1.0;
    var last = 0u;
    var g_rgb = vec3<f32>(0.0);
    var g_alpha = 0.0;
    var g_depth = 0.0;
    if (inside) {
        let p = py * pc.width + px;
        t = final_t[p];
        last = last_in[p];
        g_rgb = vec3<f32>(d_rgb[3u * p], d_rgb[3u * p + 1u], d_rgb[3u * p + 2u]);
        g_alpha = d_alpha[p];
        g_depth = d_depth[p];
    }
    init_grads(lid);
    if (lid == 0u) {
        atomicStore(&max_last, 0u);
    }
    workgroupBarrier();
    atomicMax(&max_last, last);
    workgroupBarrier();
    if (lid == 0u) {
        max_last_plain = atomicLoad(&max_last);
        chunk_plain = chunk_size(nsg);
    }
    let n = workgroupUniformLoad(&max_last_plain);
    let chunk_len = workgroupUniformLoad(&chunk_plain);
    // Colour, depth and coverage behind the current Gaussian.
    var behind_rgb = pc.background.xyz;
    var behind_depth = 0.0;
    var behind_alpha = 0.0;

    let batches = (n + BATCH - 1u) / BATCH;
    for (var bi = 0u; bi < batches; bi = bi + 1u) {
        let b = batches - 1u - bi;
        let first = b * BATCH;
        let count = min(BATCH, n - first);
        workgroupBarrier(); // the previous batch is consumed
        if (lid < count) {
            let g = ids[start + first + lid];
            s_id[lid] = g;
            s_xy_op[lid] = proj[3u * g];
            s_conic[lid] = proj[3u * g + 1u];
            s_colour[lid] = proj[3u * g + 2u];
        }
        workgroupBarrier();
        // Back to front, in chunks.
        for (var c0 = 0u; c0 < count; c0 = c0 + chunk_len) {
            let chunk = min(chunk_len, count - c0);
            for (var j = 0u; j < chunk; j = j + 1u) {
                let k = count - 1u - (c0 + j);
                var contributes = false;
                var grad = array<f32, 10>(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
                if (first + k < last) {
                    let xo = s_xy_op[k];
                    let co = s_conic[k].xyz;
                    let d = xo.xy - pix;
                    let power = 0.5 * (co.x * d.x * d.x + co.z * d.y * d.y) + co.y * d.x * d.y;
                    let gauss = exp(-power);
                    let raw = xo.w * gauss;
                    let alpha = min(pc.alpha_max, raw);
                    if (power >= 0.0 && alpha >= pc.min_alpha) {
                        contributes = true;
                        let one_minus = 1.0 - alpha;
                        let t_i = t / one_minus;
                        let w = alpha * t_i;
                        let col = s_colour[k].xyz;
                        let g_a = t_i * (dot(g_rgb, col - behind_rgb) + g_depth * (xo.z - behind_depth)
                            + g_alpha * (1.0 - behind_alpha));
                        behind_rgb = col * alpha + behind_rgb * one_minus;
                        behind_depth = xo.z * alpha + behind_depth * one_minus;
                        behind_alpha = alpha + behind_alpha * one_minus;
                        t = t_i;
                        if (raw < pc.alpha_max) {
                            let g_power = -alpha * g_a;
                            grad[0] = g_power * (co.x * d.x + co.y * d.y);
                            grad[1] = g_power * (co.z * d.y + co.y * d.x);
                            grad[2] = g_power * 0.5 * d.x * d.x;
                            grad[3] = g_power * d.x * d.y;
                            grad[4] = g_power * 0.5 * d.y * d.y;
                            grad[5] = g_a * gauss;
                        }
                        grad[6] = g_rgb.x * w;
                        grad[7] = g_rgb.y * w;
                        grad[8] = g_rgb.z * w;
                        grad[9] = g_depth * w;
                    }
                }
                if (subgroupAny(contributes)) {
                    for (var c = 0u; c < 10u; c = c + 1u) {
                        store_grad(sg, nsg, lane, j, s_id[k], c, subgroupAdd(grad[c]));
                    }
                }
            }
            flush_grads(lid, chunk, nsg, start + first + count - 1u - c0);
        }
    }
}
