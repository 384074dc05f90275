// Front-to-back blending of the rasteriser (host side: engine/src/ops/raster/). One workgroup
// per 16x16 tile, one invocation per pixel. The tile's sorted Gaussians are staged through
// workgroup memory 256 at a time (each invocation loads one); every pixel walks the batch in
// order. For each Gaussian: power = (a dx^2 + c dy^2) / 2 + b dx dy with d = centre - pixel
// centre, alpha = min(alpha_max, o exp(-power)); alpha below min_alpha is skipped; a Gaussian
// that would bring the transmittance T below t_stop ends the pixel without being blended.
// C = sum c_i alpha_i T_i + T bg, A = 1 - T, D = sum z_i alpha_i T_i. The workgroup stops as
// soon as every pixel is done. The backward pass needs the final T and `last`, the number of
// tile entries up to and including the pixel's last blended Gaussian.

// @include raster_blend_params.wgsl

@group(0) @binding(0) var<storage, read> ranges: array<u32>;
@group(0) @binding(1) var<storage, read> ids: array<u32>;
@group(0) @binding(2) var<storage, read> proj: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> rgb: array<f32>;
@group(0) @binding(4) var<storage, read_write> alpha_out: array<f32>;
@group(0) @binding(5) var<storage, read_write> depth_out: array<f32>;
@group(0) @binding(6) var<storage, read_write> final_t: array<f32>;
@group(0) @binding(7) var<storage, read_write> last_out: array<u32>;
var<immediate> pc: Params;

const BATCH: u32 = 256u;

var<workgroup> s_xy_op: array<vec4<f32>, BATCH>;   // u, v, depth, opacity
var<workgroup> s_conic: array<vec4<f32>, BATCH>;   // a, b, c
var<workgroup> s_colour: array<vec4<f32>, BATCH>;
var<workgroup> n_done: atomic<u32>;
var<workgroup> all_done: u32;

@compute @workgroup_size(16, 16)
fn blend(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) loc: vec3<u32>,
         @builtin(local_invocation_index) lid: u32) {
    let tile = wid.y * pc.tiles_x + wid.x;
    let px = wid.x * 16u + loc.x;
    let py = wid.y * 16u + loc.y;
    let inside = px < pc.width && py < pc.height;
    let pix = vec2<f32>(f32(px) + 0.5, f32(py) + 0.5);
    let start = ranges[2u * tile];
    let end = max(ranges[2u * tile + 1u], start);
    let batches = (end - start + BATCH - 1u) / BATCH;

    if (lid == 0u) {
        atomicStore(&n_done, 0u);
    }
    workgroupBarrier();
    var done = !inside;
    if (done) {
        atomicAdd(&n_done, 1u);
    }
    var t = 1.0;
    var colour = vec3<f32>(0.0);
    var depth = 0.0;
    var last = 0u;
    for (var b = 0u; b < batches; b = b + 1u) {
        workgroupBarrier(); // the previous batch is consumed, every `done` counted
        if (lid == 0u) {
            all_done = atomicLoad(&n_done);
        }
        let i = start + b * BATCH + lid;
        if (i < end) {
            let g = ids[i];
            s_xy_op[lid] = proj[3u * g];
            s_conic[lid] = proj[3u * g + 1u];
            s_colour[lid] = proj[3u * g + 2u];
        }
        if (workgroupUniformLoad(&all_done) == 256u) {
            break;
        }
        let count = min(BATCH, end - start - b * BATCH);
        for (var k = 0u; k < count; k = k + 1u) {
            if (done) {
                break;
            }
            let xo = s_xy_op[k];
            let co = s_conic[k].xyz;
            let d = xo.xy - pix;
            let power = 0.5 * (co.x * d.x * d.x + co.z * d.y * d.y) + co.y * d.x * d.y;
            if (power < 0.0) {
                continue;
            }
            let alpha = min(pc.alpha_max, xo.w * exp(-power));
            if (alpha < pc.min_alpha) {
                continue;
            }
            let next_t = t * (1.0 - alpha);
            if (next_t < pc.t_stop) {
                done = true;
                atomicAdd(&n_done, 1u);
                break;
            }
            let w = alpha * t;
            colour += w * s_colour[k].xyz;
            depth += w * xo.z;
            t = next_t;
            last = b * BATCH + k + 1u;
        }
    }
    if (inside) {
        let p = py * pc.width + px;
        let c = colour + t * pc.background.xyz;
        rgb[3u * p] = c.x;
        rgb[3u * p + 1u] = c.y;
        rgb[3u * p + 2u] = c.z;
        alpha_out[p] = 1.0 - t;
        depth_out[p] = depth;
        final_t[p] = t;
        last_out[p] = last;
    }
}
