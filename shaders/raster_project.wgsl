// Gaussian projection for the tile rasteriser (host side: engine/src/ops/raster/), forward
// and backward. One invocation per Gaussian.
//
// `project`: EWA splatting. The 3D covariance S = M M^T with M = R(q) diag(exp(log_scale)) is
// taken to camera space by the world-to-camera rotation W and to the image by the Jacobian J
// of the pinhole projection at the camera-space mean t: S2 = J W S W^T J^T + dilation * I.
// J uses x/z and y/z clamped to 1.3x the field of view, so Gaussians far off screen do not get
// huge footprints. A Gaussian reaches a pixel only where its alpha o * exp(-d^T S2^-1 d / 2)
// is at least `min_alpha`, i.e. inside the ellipse d^T S2^-1 d <= 2 ln(o / min_alpha), whose
// bounding box is +-sqrt(q S2_xx), +-sqrt(q S2_yy): that box decides the tiles. Culling
// follows a fixed order, the same as the CPU reference: invalid input (NaN, Inf, zero
// quaternion), behind the near plane, too faint (opacity < min_alpha), degenerate projection
// (determinant below min_det or not finite), outside the image, too many tiles. Each reason has
// a counter in `stats` (0 drawn, 1 invalid, 2 behind, 3 faint, 4 outside, 5 too many tiles).
//
// `project_backward`: the chain rule back from the per-Gaussian image-space gradients that the
// blend backward accumulated (du, dv, conic a b c, opacity, rgb, depth) to the parameters.

struct Params {
    rot0: vec4<f32>, // world-to-camera rotation, one row per vec4, translation in w
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    intr: vec4<f32>, // fx, fy, cx, cy (pixel centres at integer + 0.5)
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
    n: u32,
    near: f32,
    min_alpha: f32,
    max_tiles: u32,
    dilation: f32,
    min_det: f32,
    pad0: u32,
    pad1: u32,
}

@group(0) @binding(0) var<storage, read> means: array<f32>;
@group(0) @binding(1) var<storage, read> log_scales: array<f32>;
@group(0) @binding(2) var<storage, read> quats: array<f32>;
@group(0) @binding(3) var<storage, read> opacities: array<f32>; // logits
@group(0) @binding(4) var<storage, read> colours: array<f32>;
// Per Gaussian, three vec4: (u, v, depth, opacity), (conic a, b, c, 0), (r, g, b, 0).
@group(0) @binding(5) var<storage, read_write> proj: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> counts: array<u32>;
// Tile rectangle, min corner and exclusive max corner, 16 bits each: (x0 | y0 << 16, x1 | y1 << 16).
@group(0) @binding(7) var<storage, read_write> rects: array<vec2<u32>>;
@group(0) @binding(8) var<storage, read_write> stats: array<atomic<u32>>;
// Per Gaussian: du, dv, da, db, dc, d opacity, dr, dg, db, d depth.
@group(0) @binding(9) var<storage, read> grad2d: array<f32>;
@group(0) @binding(10) var<storage, read_write> d_means: array<f32>;
@group(0) @binding(11) var<storage, read_write> d_log_scales: array<f32>;
@group(0) @binding(12) var<storage, read_write> d_quats: array<f32>;
@group(0) @binding(13) var<storage, read_write> d_opacities: array<f32>;
@group(0) @binding(14) var<storage, read_write> d_colours: array<f32>;
var<immediate> pc: Params;

const TILE: u32 = 16u;
const STAT_DRAWN: u32 = 0u;
const STAT_INVALID: u32 = 1u;
const STAT_BEHIND: u32 = 2u;
const STAT_FAINT: u32 = 3u;
const STAT_OUTSIDE: u32 = 4u;
const STAT_TOO_MANY_TILES: u32 = 5u;

// By bits, so that no compiler can fold the test away.
fn finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

fn finite3(v: vec3<f32>) -> bool {
    return finite(v.x) && finite(v.y) && finite(v.z);
}

// Rotation of the unit quaternion (w, x, y, z); WGSL matrices are built from columns.
fn quat_to_rot(q: vec4<f32>) -> mat3x3<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    return mat3x3<f32>(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
}

fn world_to_camera() -> mat3x3<f32> {
    return transpose(mat3x3<f32>(pc.rot0.xyz, pc.rot1.xyz, pc.rot2.xyz));
}

fn load3(a: u32, which: u32) -> vec3<f32> {
    switch which {
        case 0u: { return vec3<f32>(means[3u * a], means[3u * a + 1u], means[3u * a + 2u]); }
        case 1u: { return vec3<f32>(log_scales[3u * a], log_scales[3u * a + 1u], log_scales[3u * a + 2u]); }
        default: { return vec3<f32>(colours[3u * a], colours[3u * a + 1u], colours[3u * a + 2u]); }
    }
}

fn load_quat(g: u32) -> vec4<f32> {
    return vec4<f32>(quats[4u * g], quats[4u * g + 1u], quats[4u * g + 2u], quats[4u * g + 3u]);
}

// x/z and y/z clamped to the field of view widened by 30 % on each side.
fn clamped_ratios(t: vec3<f32>) -> vec2<f32> {
    let fx = pc.intr.x;
    let fy = pc.intr.y;
    let tan_x = 0.5 * f32(pc.width) / fx;
    let tan_y = 0.5 * f32(pc.height) / fy;
    let lim_x_pos = (f32(pc.width) - pc.intr.z) / fx + 0.3 * tan_x;
    let lim_x_neg = pc.intr.z / fx + 0.3 * tan_x;
    let lim_y_pos = (f32(pc.height) - pc.intr.w) / fy + 0.3 * tan_y;
    let lim_y_neg = pc.intr.w / fy + 0.3 * tan_y;
    return vec2<f32>(clamp(t.x / t.z, -lim_x_neg, lim_x_pos), clamp(t.y / t.z, -lim_y_neg, lim_y_pos));
}

// The 2x3 Jacobian of the projection at t (as 3 columns of 2).
fn jacobian(t: vec3<f32>) -> mat3x2<f32> {
    let r = clamped_ratios(t);
    let fx = pc.intr.x;
    let fy = pc.intr.y;
    return mat3x2<f32>(vec2<f32>(fx / t.z, 0.0), vec2<f32>(0.0, fy / t.z),
                       vec2<f32>(-fx * r.x / t.z, -fy * r.y / t.z));
}

var<workgroup> local_stats: array<atomic<u32>, 6>;

fn count_stat(which: u32) {
    atomicAdd(&local_stats[which], 1u);
}

@compute @workgroup_size(256)
fn project(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
           @builtin(local_invocation_index) lid: u32) {
    if (lid < 6u) {
        atomicStore(&local_stats[lid], 0u);
    }
    workgroupBarrier();
    let g = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (g < pc.n) {
        project_one(g);
    }
    workgroupBarrier();
    if (lid < 6u) {
        let c = atomicLoad(&local_stats[lid]);
        if (c > 0u) {
            atomicAdd(&stats[lid], c);
        }
    }
}

fn cull(g: u32, why: u32) {
    counts[g] = 0u;
    count_stat(why);
}

fn project_one(g: u32) {
    let mean = load3(g, 0u);
    let log_scale = load3(g, 1u);
    let colour = load3(g, 2u);
    let q_raw = load_quat(g);
    let logit = opacities[g];
    let q_norm2 = dot(q_raw, q_raw);
    if (!(finite3(mean) && finite3(log_scale) && finite3(colour) && finite(logit) && finite(q_raw.x)
          && finite(q_raw.y) && finite(q_raw.z) && finite(q_raw.w) && finite(q_norm2))
        || q_norm2 < 1e-24) {
        cull(g, STAT_INVALID);
        return;
    }
    let w2c = world_to_camera();
    let t = w2c * mean + vec3<f32>(pc.rot0.w, pc.rot1.w, pc.rot2.w);
    if (!finite3(t)) {
        cull(g, STAT_INVALID);
        return;
    }
    if (t.z < pc.near) {
        cull(g, STAT_BEHIND);
        return;
    }
    let opacity = 1.0 / (1.0 + exp(-logit));
    if (opacity < pc.min_alpha) {
        cull(g, STAT_FAINT);
        return;
    }
    let rot = quat_to_rot(q_raw * inverseSqrt(q_norm2));
    let s = exp(log_scale);
    let m = mat3x3<f32>(rot[0] * s.x, rot[1] * s.y, rot[2] * s.z);
    let cov_cam = w2c * (m * transpose(m)) * transpose(w2c);
    let j = jacobian(t);
    let cov = j * cov_cam * transpose(j);
    let a = cov[0][0] + pc.dilation;
    let b = cov[1][0];
    let c = cov[1][1] + pc.dilation;
    let det = a * c - b * b;
    let u = pc.intr.x * t.x / t.z + pc.intr.z;
    let v = pc.intr.y * t.y / t.z + pc.intr.w;
    if (!(finite(det) && finite(a) && finite(c) && finite(u) && finite(v)) || det < pc.min_det) {
        cull(g, STAT_INVALID);
        return;
    }
    let conic = vec3<f32>(c / det, -b / det, a / det);
    // Extent where alpha >= min_alpha.
    let q = 2.0 * log(opacity / pc.min_alpha);
    let rx = sqrt(q * a);
    let ry = sqrt(q * c);
    // Pixels whose centres (p + 0.5) lie in [u - rx, u + rx], clamped in float before any
    // conversion (an out-of-range float-to-int conversion is undefined).
    let w = f32(pc.width);
    let h = f32(pc.height);
    let px0 = clamp(ceil(u - rx - 0.5), -1.0, w);
    let px1 = clamp(floor(u + rx - 0.5), -1.0, w);
    let py0 = clamp(ceil(v - ry - 0.5), -1.0, h);
    let py1 = clamp(floor(v + ry - 0.5), -1.0, h);
    if (px1 < 0.0 || py1 < 0.0 || px0 > w - 1.0 || py0 > h - 1.0 || px0 > px1 || py0 > py1) {
        cull(g, STAT_OUTSIDE);
        return;
    }
    let x0 = u32(max(px0, 0.0)) / TILE;
    let y0 = u32(max(py0, 0.0)) / TILE;
    let x1 = u32(min(px1, w - 1.0)) / TILE + 1u;
    let y1 = u32(min(py1, h - 1.0)) / TILE + 1u;
    let tiles = (x1 - x0) * (y1 - y0);
    if (tiles > pc.max_tiles) {
        cull(g, STAT_TOO_MANY_TILES);
        return;
    }
    counts[g] = tiles;
    rects[g] = vec2<u32>(x0 | (y0 << 16u), x1 | (y1 << 16u));
    proj[3u * g] = vec4<f32>(u, v, t.z, opacity);
    proj[3u * g + 1u] = vec4<f32>(conic, 0.0);
    // Negative colours clamp to 0, as 3D Gaussian splatting clamps its spherical-harmonic colour.
    proj[3u * g + 2u] = vec4<f32>(max(colour, vec3<f32>(0.0)), 0.0);
    count_stat(STAT_DRAWN);
}

// Backward of the projection for one drawn Gaussian; the others get zero gradients.
@compute @workgroup_size(256)
fn project_backward(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                    @builtin(local_invocation_index) lid: u32) {
    let g = (wid.x + wid.y * nwg.x) * 256u + lid;
    if (g >= pc.n) {
        return;
    }
    if (counts[g] == 0u) {
        for (var k = 0u; k < 3u; k = k + 1u) {
            d_means[3u * g + k] = 0.0;
            d_log_scales[3u * g + k] = 0.0;
            d_colours[3u * g + k] = 0.0;
        }
        for (var k = 0u; k < 4u; k = k + 1u) {
            d_quats[4u * g + k] = 0.0;
        }
        d_opacities[g] = 0.0;
        return;
    }
    let base = 10u * g;
    let d_uv = vec2<f32>(grad2d[base], grad2d[base + 1u]);
    let d_conic = vec3<f32>(grad2d[base + 2u], grad2d[base + 3u], grad2d[base + 4u]);
    let d_opacity = grad2d[base + 5u];
    let d_depth = grad2d[base + 9u];
    for (var k = 0u; k < 3u; k = k + 1u) {
        // A clamped channel passes no gradient.
        d_colours[3u * g + k] = select(grad2d[base + 6u + k], 0.0, colours[3u * g + k] < 0.0);
    }

    // Recompute the forward quantities.
    let mean = load3(g, 0u);
    let log_scale = load3(g, 1u);
    let q_raw = load_quat(g);
    let q_len = sqrt(dot(q_raw, q_raw));
    let qn = q_raw / q_len;
    let w2c = world_to_camera();
    let t = w2c * mean + vec3<f32>(pc.rot0.w, pc.rot1.w, pc.rot2.w);
    let opacity = 1.0 / (1.0 + exp(-opacities[g]));
    d_opacities[g] = d_opacity * opacity * (1.0 - opacity);
    let rot = quat_to_rot(qn);
    let s = exp(log_scale);
    let m = mat3x3<f32>(rot[0] * s.x, rot[1] * s.y, rot[2] * s.z);
    let sigma = m * transpose(m);
    let cov_cam = w2c * sigma * transpose(w2c);
    let j = jacobian(t);
    let cov = j * cov_cam * transpose(j) + mat2x2<f32>(vec2<f32>(pc.dilation, 0.0), vec2<f32>(0.0, pc.dilation));
    let det = cov[0][0] * cov[1][1] - cov[1][0] * cov[1][0];
    let conic = mat2x2<f32>(vec2<f32>(cov[1][1], -cov[1][0]), vec2<f32>(-cov[1][0], cov[0][0])) * (1.0 / det);

    // Conic -> 2D covariance: dL/dS2 = -Q G Q, G the gradient as a symmetric matrix (the
    // off-diagonal b enters power as b dx dy, so each off-diagonal entry carries half of it).
    let g_q = mat2x2<f32>(vec2<f32>(d_conic.x, 0.5 * d_conic.y), vec2<f32>(0.5 * d_conic.y, d_conic.z));
    let g_cov = -1.0 * (conic * g_q * conic);
    // S2 = J Sc J^T: dJ = 2 G2 J Sc, dSc = J^T G2 J.
    let g_j = 2.0 * (g_cov * j * cov_cam);
    let g_cov_cam = transpose(j) * g_cov * j;
    // Sc = W S W^T, S = M M^T.
    let g_sigma = transpose(w2c) * g_cov_cam * w2c;
    let g_m = 2.0 * (g_sigma * m);
    let g_rot = mat3x3<f32>(g_m[0] * s.x, g_m[1] * s.y, g_m[2] * s.z);
    let g_s = vec3<f32>(dot(g_m[0], rot[0]), dot(g_m[1], rot[1]), dot(g_m[2], rot[2]));
    let g_log_scale = g_s * s;
    for (var k = 0u; k < 3u; k = k + 1u) {
        d_log_scales[3u * g + k] = g_log_scale[k];
    }

    // Rotation -> normalised quaternion (entry R[r][c] is g_rot[c][r]) -> raw quaternion.
    let w = qn.x;
    let x = qn.y;
    let y = qn.z;
    let z = qn.w;
    let r00 = g_rot[0][0];
    let r01 = g_rot[1][0];
    let r02 = g_rot[2][0];
    let r10 = g_rot[0][1];
    let r11 = g_rot[1][1];
    let r12 = g_rot[2][1];
    let r20 = g_rot[0][2];
    let r21 = g_rot[1][2];
    let r22 = g_rot[2][2];
    let g_qn = 2.0 * vec4<f32>(
        -z * r01 + y * r02 + z * r10 - x * r12 - y * r20 + x * r21,
        y * r01 + z * r02 + y * r10 - 2.0 * x * r11 - w * r12 + z * r20 + w * r21 - 2.0 * x * r22,
        -2.0 * y * r00 + x * r01 + w * r02 + x * r10 + z * r12 - w * r20 + z * r21 - 2.0 * y * r22,
        -2.0 * z * r00 - w * r01 + x * r02 + w * r10 - 2.0 * z * r11 + y * r12 + x * r20 + y * r21,
    );
    let g_quat = (g_qn - qn * dot(qn, g_qn)) / q_len;
    for (var k = 0u; k < 4u; k = k + 1u) {
        d_quats[4u * g + k] = g_quat[k];
    }

    // Camera-space mean: from (u, v), depth and the Jacobian.
    let fx = pc.intr.x;
    let fy = pc.intr.y;
    let iz = 1.0 / t.z;
    var g_t = vec3<f32>(fx * iz * d_uv.x, fy * iz * d_uv.y,
                        -fx * t.x * iz * iz * d_uv.x - fy * t.y * iz * iz * d_uv.y + d_depth);
    let r = clamped_ratios(t);
    g_t.z += -fx * iz * iz * g_j[0][0] - fy * iz * iz * g_j[1][1]
        + fx * r.x * iz * iz * g_j[2][0] + fy * r.y * iz * iz * g_j[2][1];
    if (r.x == t.x / t.z) {
        g_t.x += -fx * iz * iz * g_j[2][0];
        g_t.z += fx * t.x * iz * iz * iz * g_j[2][0];
    }
    if (r.y == t.y / t.z) {
        g_t.y += -fy * iz * iz * g_j[2][1];
        g_t.z += fy * t.y * iz * iz * iz * g_j[2][1];
    }
    let g_mean = transpose(w2c) * g_t;
    for (var k = 0u; k < 3u; k = k + 1u) {
        d_means[3u * g + k] = g_mean[k];
    }
}
