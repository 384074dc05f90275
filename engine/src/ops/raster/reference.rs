//! The f64 CPU rasteriser the kernels are checked against: the same rules as the GPU (the
//! same culling order and guards, the same tile lists, the same depth keys and so the same
//! blending order), in plain loops, forward and backward.

// Index loops read as the formulas they implement.
#![allow(clippy::needless_range_loop)]

use super::{
    Camera, GaussianData, GaussianSet, ALPHA_MAX, DILATION, MAX_TILES_PER_GAUSSIAN, MIN_ALPHA, MIN_DET,
    MIN_QUAT_NORM2, NEAR, TILE, T_STOP,
};

type M3 = [[f64; 3]; 3];

/// Finite in f32: the GPU computes in f32, so a value beyond f32's range is as non-finite to
/// the reference as it is to the kernels.
fn fits(v: f64) -> bool {
    (v as f32).is_finite()
}

fn mul(a: &M3, b: &M3) -> M3 {
    let mut c = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    c
}
fn tr(a: &M3) -> M3 {
    let mut c = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = a[j][i];
        }
    }
    c
}
fn mv(a: &M3, v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| a[i][0] * v[0] + a[i][1] * v[1] + a[i][2] * v[2])
}

/// Gaussian parameters in f64 (finite differences perturb these).
pub type Scene = GaussianSet<Vec<f64>>;

impl Scene {
    pub fn from_data(g: &GaussianData) -> Scene {
        GaussianSet::from_fields(g.fields().map(|v| v.iter().map(|&x| x as f64).collect()))
    }
    pub fn len(&self) -> usize {
        self.opacities.len()
    }
    pub fn is_empty(&self) -> bool {
        self.opacities.is_empty()
    }
}

/// A drawn Gaussian on screen.
#[derive(Clone, Copy, Debug)]
pub struct Splat {
    pub uv: [f64; 2],
    pub depth: f64,
    pub opacity: f64,
    pub conic: [f64; 3],
    pub colour: [f64; 3],
    /// Tiles x0..x1, y0..y1 (exclusive ends).
    pub rect: [u32; 4],
}

/// Why a Gaussian was dropped, in the order the rules are applied (the GPU's `stats` order).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dropped {
    Invalid,
    Behind,
    Faint,
    Outside,
    TooManyTiles,
}

/// Per-Gaussian intermediate values of the projection, kept for the backward pass.
struct Geometry {
    w2c: M3,
    t: [f64; 3],
    qn: [f64; 4],
    q_len: f64,
    rot: M3,
    s: [f64; 3],
    m: M3,
    cov_cam: M3,
    j: [[f64; 3]; 2],
    ratios: [f64; 2],
    clamped: [bool; 2],
    cov: [f64; 3],
}

fn quat_to_rot(q: [f64; 4]) -> M3 {
    let [w, x, y, z] = q;
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

fn camera_matrix(cam: &Camera) -> (M3, [f64; 3]) {
    let r = cam.rotation.map(|row| row.map(|v| v as f64));
    (r, cam.translation.map(|v| v as f64))
}

fn geometry(s: &Scene, i: usize, cam: &Camera) -> Geometry {
    let (w2c, tc) = camera_matrix(cam);
    let mean = [s.means[3 * i], s.means[3 * i + 1], s.means[3 * i + 2]];
    let tm = mv(&w2c, mean);
    let t = [tm[0] + tc[0], tm[1] + tc[1], tm[2] + tc[2]];
    let q = [0, 1, 2, 3].map(|k| s.quats[4 * i + k]);
    let q_len = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let qn = q.map(|v| v / q_len);
    let rot = quat_to_rot(qn);
    let sc = [0, 1, 2].map(|k| s.log_scales[3 * i + k].exp());
    let m = [0, 1, 2].map(|r| [0, 1, 2].map(|c| rot[r][c] * sc[c]));
    let sigma = mul(&m, &tr(&m));
    let cov_cam = mul(&mul(&w2c, &sigma), &tr(&w2c));
    let (fx, fy, cx, cy) = (cam.fx as f64, cam.fy as f64, cam.cx as f64, cam.cy as f64);
    let (w, h) = (cam.width as f64, cam.height as f64);
    let (tan_x, tan_y) = (0.5 * w / fx, 0.5 * h / fy);
    let lim_x = (-(cx / fx + 0.3 * tan_x), (w - cx) / fx + 0.3 * tan_x);
    let lim_y = (-(cy / fy + 0.3 * tan_y), (h - cy) / fy + 0.3 * tan_y);
    let (rx, ry) = (t[0] / t[2], t[1] / t[2]);
    let ratios = [rx.clamp(lim_x.0, lim_x.1), ry.clamp(lim_y.0, lim_y.1)];
    let clamped = [ratios[0] != rx, ratios[1] != ry];
    let j = [[fx / t[2], 0.0, -fx * ratios[0] / t[2]], [0.0, fy / t[2], -fy * ratios[1] / t[2]]];
    // cov = J cov_cam J^T + dilation I
    let mut cov2 = [[0.0; 2]; 2];
    for a in 0..2 {
        for b in 0..2 {
            cov2[a][b] = (0..3).map(|k| (0..3).map(|l| j[a][k] * cov_cam[k][l] * j[b][l]).sum::<f64>()).sum();
        }
    }
    let cov = [cov2[0][0] + DILATION as f64, cov2[0][1], cov2[1][1] + DILATION as f64];
    Geometry { w2c, t, qn, q_len, rot, s: sc, m, cov_cam, j, ratios, clamped, cov }
}

/// Projects Gaussian `i`, or says why it is dropped.
pub fn project_one(s: &Scene, i: usize, cam: &Camera) -> Result<Splat, Dropped> {
    let all = [&s.means[3 * i..3 * i + 3], &s.log_scales[3 * i..3 * i + 3], &s.colours[3 * i..3 * i + 3]];
    let q = &s.quats[4 * i..4 * i + 4];
    let q_norm2: f64 = q.iter().map(|v| v * v).sum();
    if all.iter().flat_map(|v| v.iter()).chain(q).any(|v| !v.is_finite())
        || !s.opacities[i].is_finite()
        || !q_norm2.is_finite()
        || q_norm2 < MIN_QUAT_NORM2 as f64
    {
        return Err(Dropped::Invalid);
    }
    let g = geometry(s, i, cam);
    let t = g.t;
    if !t.iter().all(|&v| fits(v)) {
        return Err(Dropped::Invalid);
    }
    if t[2] < NEAR as f64 {
        return Err(Dropped::Behind);
    }
    let opacity = 1.0 / (1.0 + (-s.opacities[i]).exp());
    if opacity < MIN_ALPHA as f64 {
        return Err(Dropped::Faint);
    }
    let [a, b, c] = g.cov;
    let det = a * c - b * b;
    let u = cam.fx as f64 * t[0] / t[2] + cam.cx as f64;
    let v = cam.fy as f64 * t[1] / t[2] + cam.cy as f64;
    if ![det, a, c, u, v].iter().all(|&x| fits(x)) || det < MIN_DET as f64 {
        return Err(Dropped::Invalid);
    }
    let conic = [c / det, -b / det, a / det];
    let q = 2.0 * (opacity / MIN_ALPHA as f64).ln();
    let (rx, ry) = ((q * a).sqrt(), (q * c).sqrt());
    let (w, h) = (cam.width as f64, cam.height as f64);
    let px0 = (u - rx - 0.5).ceil().clamp(-1.0, w);
    let px1 = (u + rx - 0.5).floor().clamp(-1.0, w);
    let py0 = (v - ry - 0.5).ceil().clamp(-1.0, h);
    let py1 = (v + ry - 0.5).floor().clamp(-1.0, h);
    if px1 < 0.0 || py1 < 0.0 || px0 > w - 1.0 || py0 > h - 1.0 || px0 > px1 || py0 > py1 {
        return Err(Dropped::Outside);
    }
    let x0 = px0.max(0.0) as u32 / TILE;
    let y0 = py0.max(0.0) as u32 / TILE;
    let x1 = px1.min(w - 1.0) as u32 / TILE + 1;
    let y1 = py1.min(h - 1.0) as u32 / TILE + 1;
    if (x1 - x0) * (y1 - y0) > MAX_TILES_PER_GAUSSIAN {
        return Err(Dropped::TooManyTiles);
    }
    // Negative colours clamp to 0, as 3D Gaussian splatting clamps its spherical-harmonic colour.
    let colour = [0, 1, 2].map(|k| s.colours[3 * i + k].max(0.0));
    Ok(Splat { uv: [u, v], depth: t[2], opacity, conic, colour, rect: [x0, x1, y0, y1] })
}

/// Per-Gaussian results and counts in the GPU's order: drawn, invalid, behind, faint,
/// outside, too many tiles.
pub fn project(s: &Scene, cam: &Camera) -> (Vec<Result<Splat, Dropped>>, [u32; 6]) {
    let out: Vec<_> = (0..s.len()).map(|i| project_one(s, i, cam)).collect();
    let mut counts = [0u32; 6];
    for r in &out {
        let k = match r {
            Ok(_) => 0,
            Err(Dropped::Invalid) => 1,
            Err(Dropped::Behind) => 2,
            Err(Dropped::Faint) => 3,
            Err(Dropped::Outside) => 4,
            Err(Dropped::TooManyTiles) => 5,
        };
        counts[k] += 1;
    }
    (out, counts)
}

/// Each tile's Gaussians in blending order: by depth (as f32, the precision the GPU sorts
/// in), then by index.
pub fn tile_lists(splats: &[Result<Splat, Dropped>], cam: &Camera) -> Vec<Vec<usize>> {
    let (tx, ty) = cam.tiles();
    let mut lists = vec![Vec::new(); (tx * ty) as usize];
    for (i, s) in splats.iter().enumerate() {
        if let Ok(s) = s {
            for y in s.rect[2]..s.rect[3] {
                for x in s.rect[0]..s.rect[1] {
                    lists[(y * tx + x) as usize].push(i);
                }
            }
        }
    }
    let key = |i: usize| splats[i].as_ref().map(|s| (s.depth as f32).to_bits()).unwrap_or(0);
    for l in &mut lists {
        l.sort_by_key(|&i| (key(i), i));
    }
    lists
}

/// Alpha of a splat at a pixel centre, and exp(-power), or None where it is skipped.
fn alpha_at(s: &Splat, pix: [f64; 2]) -> Option<(f64, f64, [f64; 2])> {
    let d = [s.uv[0] - pix[0], s.uv[1] - pix[1]];
    let power = 0.5 * (s.conic[0] * d[0] * d[0] + s.conic[2] * d[1] * d[1]) + s.conic[1] * d[0] * d[1];
    if power < 0.0 {
        return None;
    }
    let gauss = (-power).exp();
    let alpha = (s.opacity * gauss).min(ALPHA_MAX as f64);
    (alpha >= MIN_ALPHA as f64).then_some((alpha, gauss, d))
}

/// The reference image: rgb `[H, W, 3]`, alpha and depth `[H, W]`, and the drop counts.
#[derive(Clone, Debug)]
pub struct Image {
    pub rgb: Vec<f64>,
    pub alpha: Vec<f64>,
    pub depth: Vec<f64>,
    pub counts: [u32; 6],
    pub intersections: usize,
}

/// Renders the scene by the GPU's rules.
pub fn render(s: &Scene, cam: &Camera, background: [f32; 3]) -> Image {
    let (splats, counts) = project(s, cam);
    let lists = tile_lists(&splats, cam);
    let (w, h) = (cam.width as usize, cam.height as usize);
    let tx = cam.tiles().0 as usize;
    let bg = background.map(|v| v as f64);
    let mut img = Image {
        rgb: vec![0.0; h * w * 3],
        alpha: vec![0.0; h * w],
        depth: vec![0.0; h * w],
        counts,
        intersections: lists.iter().map(Vec::len).sum(),
    };
    for py in 0..h {
        for px in 0..w {
            let (c, a, d) =
                pixel(&splats, &lists[(py / TILE as usize) * tx + px / TILE as usize], px, py, bg);
            let p = py * w + px;
            img.rgb[3 * p..3 * p + 3].copy_from_slice(&c);
            img.alpha[p] = a;
            img.depth[p] = d;
        }
    }
    img
}

/// One pixel's (rgb, alpha, depth) from its tile's list.
fn pixel(
    splats: &[Result<Splat, Dropped>],
    list: &[usize],
    px: usize,
    py: usize,
    bg: [f64; 3],
) -> ([f64; 3], f64, f64) {
    let pix = [px as f64 + 0.5, py as f64 + 0.5];
    let (mut t, mut c, mut d) = (1.0, [0.0; 3], 0.0);
    for &i in list {
        let sp = splats[i].as_ref().unwrap();
        let Some((alpha, _, _)) = alpha_at(sp, pix) else { continue };
        let next = t * (1.0 - alpha);
        if next < T_STOP as f64 {
            break;
        }
        for k in 0..3 {
            c[k] += alpha * t * sp.colour[k];
        }
        d += alpha * t * sp.depth;
        t = next;
    }
    ([0, 1, 2].map(|k| c[k] + t * bg[k]), 1.0 - t, d)
}

/// (rgb, alpha, depth) of the given (x, y) pixels only: for checking large images on a sample.
pub fn render_pixels(
    s: &Scene,
    cam: &Camera,
    background: [f32; 3],
    pixels: &[(u32, u32)],
) -> Vec<([f64; 3], f64, f64)> {
    let (splats, _) = project(s, cam);
    let lists = tile_lists(&splats, cam);
    let tx = cam.tiles().0;
    let bg = background.map(|v| v as f64);
    pixels
        .iter()
        .map(|&(x, y)| {
            pixel(&splats, &lists[((y / TILE) * tx + x / TILE) as usize], x as usize, y as usize, bg)
        })
        .collect()
}

/// Gradients with respect to every quantity of a [`Scene`].
pub type Grads = GaussianSet<Vec<f64>>;

/// Backward of [`render`] for the loss sum(d_rgb * rgb) + sum(d_alpha * alpha) +
/// sum(d_depth * depth): per pixel back to front, then per Gaussian through the projection.
pub fn render_backward(
    s: &Scene,
    cam: &Camera,
    background: [f32; 3],
    d_rgb: &[f64],
    d_alpha: &[f64],
    d_depth: &[f64],
) -> Grads {
    let (splats, _) = project(s, cam);
    let lists = tile_lists(&splats, cam);
    let (w, h) = (cam.width as usize, cam.height as usize);
    let tx = cam.tiles().0 as usize;
    let bg = background.map(|v| v as f64);
    let n = s.len();
    // du, dv, conic a b c, opacity, rgb, depth
    let mut g2 = vec![[0.0f64; 10]; n];
    for py in 0..h {
        for px in 0..w {
            let list = &lists[(py / TILE as usize) * tx + px / TILE as usize];
            let pix = [px as f64 + 0.5, py as f64 + 0.5];
            let p = py * w + px;
            // Forward again, keeping what was blended.
            let mut t = 1.0;
            let mut blended = Vec::new();
            for &i in list {
                let sp = splats[i].as_ref().unwrap();
                let Some((alpha, gauss, d)) = alpha_at(sp, pix) else { continue };
                let next = t * (1.0 - alpha);
                if next < T_STOP as f64 {
                    break;
                }
                blended.push((i, alpha, gauss, d));
                t = next;
            }
            let gc = [d_rgb[3 * p], d_rgb[3 * p + 1], d_rgb[3 * p + 2]];
            let (ga, gd) = (d_alpha[p], d_depth[p]);
            let (mut behind_c, mut behind_d, mut behind_a) = (bg, 0.0, 0.0);
            for &(i, alpha, gauss, d) in blended.iter().rev() {
                let sp = splats[i].as_ref().unwrap();
                let t_i = t / (1.0 - alpha);
                let wgt = alpha * t_i;
                let g_a = t_i
                    * ((0..3).map(|k| gc[k] * (sp.colour[k] - behind_c[k])).sum::<f64>()
                        + gd * (sp.depth - behind_d)
                        + ga * (1.0 - behind_a));
                for k in 0..3 {
                    behind_c[k] = sp.colour[k] * alpha + behind_c[k] * (1.0 - alpha);
                }
                behind_d = sp.depth * alpha + behind_d * (1.0 - alpha);
                behind_a = alpha + behind_a * (1.0 - alpha);
                t = t_i;
                let g = &mut g2[i];
                if sp.opacity * gauss < ALPHA_MAX as f64 {
                    let gp = -alpha * g_a;
                    let co = sp.conic;
                    g[0] += gp * (co[0] * d[0] + co[1] * d[1]);
                    g[1] += gp * (co[2] * d[1] + co[1] * d[0]);
                    g[2] += gp * 0.5 * d[0] * d[0];
                    g[3] += gp * d[0] * d[1];
                    g[4] += gp * 0.5 * d[1] * d[1];
                    g[5] += g_a * gauss;
                }
                for k in 0..3 {
                    g[6 + k] += gc[k] * wgt;
                }
                g[9] += gd * wgt;
            }
        }
    }
    let mut out = Grads {
        means: vec![0.0; 3 * n],
        log_scales: vec![0.0; 3 * n],
        quats: vec![0.0; 4 * n],
        opacities: vec![0.0; n],
        colours: vec![0.0; 3 * n],
    };
    for i in 0..n {
        if let Ok(sp) = &splats[i] {
            project_backward(s, i, cam, sp, &g2[i], &mut out);
        }
    }
    out
}

/// The chain rule from one Gaussian's image-space gradients back to its parameters.
fn project_backward(s: &Scene, i: usize, cam: &Camera, sp: &Splat, g: &[f64; 10], out: &mut Grads) {
    let geo = geometry(s, i, cam);
    for k in 0..3 {
        // A clamped channel passes no gradient.
        out.colours[3 * i + k] = if s.colours[3 * i + k] < 0.0 { 0.0 } else { g[6 + k] };
    }
    out.opacities[i] = g[5] * sp.opacity * (1.0 - sp.opacity);
    // Conic -> 2D covariance: dS2 = -Q G Q with G = [[ga, gb/2], [gb/2, gc]].
    let [a, b, c] = geo.cov;
    let det = a * c - b * b;
    let q = [[c / det, -b / det], [-b / det, a / det]];
    let gq = [[g[2], 0.5 * g[3]], [0.5 * g[3], g[4]]];
    let mut gcov = [[0.0; 2]; 2];
    for r in 0..2 {
        for cc in 0..2 {
            gcov[r][cc] =
                -(0..2).map(|k| (0..2).map(|l| q[r][k] * gq[k][l] * q[l][cc]).sum::<f64>()).sum::<f64>();
        }
    }
    // dJ = 2 G2 J Sc; dSc = J^T G2 J.
    let j = geo.j;
    let mut gj = [[0.0; 3]; 2];
    for r in 0..2 {
        for cc in 0..3 {
            gj[r][cc] = 2.0
                * (0..2)
                    .map(|k| (0..3).map(|l| gcov[r][k] * j[k][l] * geo.cov_cam[l][cc]).sum::<f64>())
                    .sum::<f64>();
        }
    }
    let mut gcc = [[0.0; 3]; 3];
    for r in 0..3 {
        for cc in 0..3 {
            gcc[r][cc] = (0..2).map(|k| (0..2).map(|l| j[k][r] * gcov[k][l] * j[l][cc]).sum::<f64>()).sum();
        }
    }
    let gsigma = mul(&mul(&tr(&geo.w2c), &gcc), &geo.w2c);
    let gm = mul(&gsigma, &geo.m).map(|row| row.map(|v| 2.0 * v));
    let mut grot = [[0.0; 3]; 3];
    for r in 0..3 {
        for cc in 0..3 {
            grot[r][cc] = gm[r][cc] * geo.s[cc];
        }
    }
    for cc in 0..3 {
        let gs: f64 = (0..3).map(|r| gm[r][cc] * geo.rot[r][cc]).sum();
        out.log_scales[3 * i + cc] = gs * geo.s[cc];
    }
    let [w, x, y, z] = geo.qn;
    let r = grot;
    let gqn = [
        2.0 * (-z * r[0][1] + y * r[0][2] + z * r[1][0] - x * r[1][2] - y * r[2][0] + x * r[2][1]),
        2.0 * (y * r[0][1] + z * r[0][2] + y * r[1][0] - 2.0 * x * r[1][1] - w * r[1][2]
            + z * r[2][0]
            + w * r[2][1]
            - 2.0 * x * r[2][2]),
        2.0 * (-2.0 * y * r[0][0] + x * r[0][1] + w * r[0][2] + x * r[1][0] + z * r[1][2] - w * r[2][0]
            + z * r[2][1]
            - 2.0 * y * r[2][2]),
        2.0 * (-2.0 * z * r[0][0] - w * r[0][1] + x * r[0][2] + w * r[1][0] - 2.0 * z * r[1][1]
            + y * r[1][2]
            + x * r[2][0]
            + y * r[2][1]),
    ];
    let dot: f64 = (0..4).map(|k| geo.qn[k] * gqn[k]).sum();
    for k in 0..4 {
        out.quats[4 * i + k] = (gqn[k] - geo.qn[k] * dot) / geo.q_len;
    }
    let (fx, fy) = (cam.fx as f64, cam.fy as f64);
    let t = geo.t;
    let iz = 1.0 / t[2];
    let mut gt =
        [fx * iz * g[0], fy * iz * g[1], -fx * t[0] * iz * iz * g[0] - fy * t[1] * iz * iz * g[1] + g[9]];
    gt[2] += -fx * iz * iz * gj[0][0] - fy * iz * iz * gj[1][1]
        + fx * geo.ratios[0] * iz * iz * gj[0][2]
        + fy * geo.ratios[1] * iz * iz * gj[1][2];
    if !geo.clamped[0] {
        gt[0] += -fx * iz * iz * gj[0][2];
        gt[2] += fx * t[0] * iz * iz * iz * gj[0][2];
    }
    if !geo.clamped[1] {
        gt[1] += -fy * iz * iz * gj[1][2];
        gt[2] += fy * t[1] * iz * iz * iz * gj[1][2];
    }
    let gmean = mv(&tr(&geo.w2c), gt);
    out.means[3 * i..3 * i + 3].copy_from_slice(&gmean);
}

/// The SH basis' constants (3D Gaussian splatting's `sh_utils`).
const SH_C1: f64 = 0.4886025119029199;
const SH_C2: [f64; 5] =
    [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396];
const SH_C3: [f64; 7] = [
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
];

/// The colour a Gaussian shows along the unit direction `dir` (from the camera to its mean):
/// its degree-0 colour `base` (0.5 + C0 f_dc) plus the higher degrees of `rest` (its `3 K`
/// coefficients: all K of red, then green, then blue, as 3D Gaussian splatting's PLY files
/// order `f_rest_*`), clamped below at 0 as 3D Gaussian splatting clamps it. `sh_colours`
/// (`shaders/sh_colour.wgsl`) and `velox view`'s shader evaluate the same sum.
pub fn sh_colour(base: [f32; 3], rest: &[f32], degree: usize, dir: [f64; 3]) -> [f64; 3] {
    let k = super::sh::per_channel(degree);
    let [x, y, z] = dir;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let mut basis = Vec::with_capacity(k);
    if degree >= 1 {
        basis.extend([-SH_C1 * y, SH_C1 * z, -SH_C1 * x]);
    }
    if degree >= 2 {
        basis.extend([
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]);
    }
    if degree >= 3 {
        basis.extend([
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]);
    }
    std::array::from_fn(|c| {
        let sum: f64 = basis.iter().enumerate().map(|(j, b)| b * rest[c * k + j] as f64).sum();
        (base[c] as f64 + sum).max(0.0)
    })
}
