//! The Gaussian rasteriser against its f64 reference and closed forms: forward on small
//! scenes, the GPU backward (every accumulation kernel) against the reference backward, stress
//! scenes sized for lavapipe, and poison inputs. Its harness row (`cases.rs`) holds the forward
//! and the deterministic backward at awkward sizes and the reference backward against finite
//! differences.
//!
//! Measured on lavapipe (NMSE): forward <= 4.3e-13, GPU backward <= 2.7e-12 (the saturated
//! scene's opacity logits excepted, see there), reference backward against central
//! differences <= 2.0e-17 (in f64). The forward is also checked against closed forms that
//! share no code with the reference: one Gaussian, a turned one, two blended by depth.

use crate::common;
use common::*;
use velox_engine::ops::norm::veto_if_over;
use velox_engine::ops::raster::{
    self, reference, render, render_backward_with, BackwardKernel, Camera, GaussianData, Gaussians, Image,
    Rendered,
};

const BG: [f32; 3] = [0.1, 0.2, 0.3];

fn camera(w: u32, h: u32) -> Camera {
    Camera::identity(60.0, w, h)
}

struct Forward {
    rendered: Rendered,
    gaussians: Gaussians,
    reference: reference::Image,
}

/// Renders on the GPU and with the reference and checks they agree.
#[track_caller]
fn check_forward(what: &str, g: &GaussianData, cam: &Camera, bound: f64) -> Forward {
    check_forward_pairs(what, g, cam, bound, 0)
}

/// [`check_forward`] allowing the tile pair count to differ by `pairs_slack`: with many
/// Gaussians, a few footprint edges fall on a pixel centre within f32 rounding, and f32 and
/// f64 then decide apart (the pixels there get alpha 1/255 either way).
#[track_caller]
fn check_forward_pairs(
    what: &str,
    g: &GaussianData,
    cam: &Camera,
    bound: f64,
    pairs_slack: usize,
) -> Forward {
    let gpu = gpu();
    let gaussians = g.upload(&gpu).unwrap();
    let rendered = render(&gpu, &gaussians, cam, BG).unwrap();
    let reference = reference::render(&reference::Scene::from_data(g), cam, BG);
    let stats = rendered.stats().unwrap();
    let counts = [
        stats.drawn,
        stats.invalid,
        stats.behind_near_plane,
        stats.too_faint,
        stats.outside_image,
        stats.too_many_tiles,
    ];
    assert_eq!(counts, reference.counts, "{what}: drop counts");
    let pairs = stats.intersections as usize;
    assert!(
        pairs.abs_diff(reference.intersections) <= pairs_slack,
        "{what}: {pairs} tile pairs, reference {}",
        reference.intersections
    );
    let img = &rendered.image;
    let rgb: Vec<f32> = img.rgb.read().unwrap();
    let alpha: Vec<f32> = img.alpha.read().unwrap();
    let depth: Vec<f32> = img.depth.read().unwrap();
    for v in rgb.iter().chain(&alpha).chain(&depth) {
        assert!(v.is_finite(), "{what}: non-finite pixel");
    }
    assert_nmse(&format!("{what} rgb"), &rgb, &reference.rgb, bound);
    assert_nmse(&format!("{what} alpha"), &alpha, &reference.alpha, bound);
    assert_nmse(&format!("{what} depth"), &depth, &reference.depth, bound);
    if pairs_slack == 0 {
        check_tile_lists(what, g, cam, img);
    }
    Forward { rendered, gaussians, reference }
}

/// The sorted pairs are the reference's to the bit: each tile's Gaussians in blending order
/// (depth, then index), and each pair's slot the place of its tile in its Gaussian's rectangle
/// (row order) after the Gaussian's offset.
#[track_caller]
fn check_tile_lists(what: &str, g: &GaussianData, cam: &Camera, img: &Image) {
    let (splats, _) = reference::project(&reference::Scene::from_data(g), cam);
    let lists = reference::tile_lists(&splats, cam);
    let (ranges, ids, slots): (Vec<u32>, Vec<u32>, Vec<u32>) =
        (img.ranges.read().unwrap(), img.ids.read().unwrap(), img.slots.read().unwrap());
    let rect = |i: usize| splats[i].as_ref().map(|s| s.rect).unwrap_or([0; 4]);
    let mut offsets = Vec::with_capacity(splats.len());
    let mut at = 0u32;
    for i in 0..splats.len() {
        offsets.push(at);
        let r = rect(i);
        at += (r[1] - r[0]) * (r[3] - r[2]);
    }
    let tx = cam.tiles().0;
    for (t, list) in lists.iter().enumerate() {
        let (a, b) =
            if list.is_empty() { (0, 0) } else { (ranges[2 * t] as usize, ranges[2 * t + 1] as usize) };
        let got: Vec<usize> = ids[a..b].iter().map(|&i| i as usize).collect();
        assert_eq!(&got, list, "{what}: tile {t}'s Gaussians in blending order");
        let (x, y) = (t as u32 % tx, t as u32 / tx);
        for (k, &i) in list.iter().enumerate() {
            let r = rect(i);
            let slot = offsets[i] + (y - r[2]) * (r[1] - r[0]) + (x - r[0]);
            assert_eq!(slots[a + k], slot, "{what}: tile {t}, pair {k}: the slot of Gaussian {i}");
        }
    }
}

/// Random gradients of the loss with respect to the image.
fn image_grads(cam: &Camera, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut rng = Rng::new(seed);
    let px = (cam.width * cam.height) as usize;
    (rng.normal_vec(3 * px), rng.normal_vec(px), rng.uniform_vec(px, -0.1, 0.1))
}

fn read_grads(g: &Gaussians) -> [Vec<f32>; 5] {
    [&g.means, &g.log_scales, &g.quats, &g.opacities, &g.colours].map(|t| t.read::<f32>().unwrap())
}

fn ref_grads(g: &reference::Grads) -> [&Vec<f64>; 5] {
    [&g.means, &g.log_scales, &g.quats, &g.opacities, &g.colours]
}

const NAMES: [&str; 5] = ["means", "log_scales", "quats", "opacities", "colours"];

/// GPU backward (every kernel) against the reference backward; the deterministic kernel twice,
/// for the same bits.
#[track_caller]
fn check_backward(what: &str, g: &GaussianData, cam: &Camera, f: &Forward, seed: u64, bound: f64) {
    let gpu = gpu();
    let (dr, da, dd) = image_grads(cam, seed);
    let (h, w) = (cam.height as usize, cam.width as usize);
    let t_dr = Tensor::from_slice(&gpu, &[h, w, 3], &dr).unwrap();
    let t_da = Tensor::from_slice(&gpu, &[h, w], &da).unwrap();
    let t_dd = Tensor::from_slice(&gpu, &[h, w], &dd).unwrap();
    let want = reference::render_backward(
        &reference::Scene::from_data(g),
        cam,
        BG,
        &f64s(&dr),
        &f64s(&da),
        &f64s(&dd),
    );
    let kernels = [
        BackwardKernel::Ordered,
        BackwardKernel::Ordered,
        BackwardKernel::CompareAndSwap,
        BackwardKernel::fastest(&gpu),
    ];
    let mut rec = gpu.recorder().unwrap();
    let grads: Vec<Gaussians> = kernels
        .iter()
        .map(|&k| render_backward_with(&mut rec, k, &f.gaussians, &f.rendered, &t_dr, &t_da, &t_dd).unwrap())
        .collect();
    rec.submit().unwrap();
    let got: Vec<[Vec<f32>; 5]> = grads.iter().map(read_grads).collect();
    assert!(
        got[0].iter().zip(&got[1]).all(|(a, b)| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())),
        "{what}: two runs of the deterministic backward differ"
    );
    for (kernel, got) in kernels.iter().zip(&got).skip(1) {
        for ((name, got), want) in NAMES.iter().zip(got).zip(ref_grads(&want)) {
            assert_nmse(&format!("{what} d{name} ({kernel:?})"), got, want, bound);
        }
    }
}

#[test]
fn forward_and_backward_match_the_reference_on_small_scenes() {
    let cam = camera(64, 48);
    let g = random_gaussians(300, 1, (-3.5, -1.5), (-2.0, 2.0));
    let f = check_forward("300 Gaussians 64x48", &g, &cam, 1e-11);
    check_backward("300 Gaussians 64x48", &g, &cam, &f, 2, 1e-10);

    // Sizes that are not multiples of the tile, a camera that is not the identity.
    let cam = Camera::look_at([0.5, -0.3, -0.5], [0.0, 0.0, 3.0], [0.0, -1.0, 0.0], 50.0, 37, 29);
    let g = random_gaussians(120, 3, (-3.0, -1.0), (-1.0, 3.0));
    let f = check_forward("120 Gaussians 37x29 look-at", &g, &cam, 1e-11);
    check_backward("120 Gaussians 37x29 look-at", &g, &cam, &f, 4, 1e-10);
}

#[test]
fn empty_scene_is_the_background() {
    let cam = camera(20, 17);
    let f = check_forward("no Gaussians", &GaussianData::default(), &cam, 0.0);
    assert_eq!(f.reference.intersections, 0);
}

#[test]
fn stress_a_million_tiny_gaussians() {
    // A million Gaussians of about a pixel, thousands per tile.
    let cam = camera(128, 96);
    let g = random_gaussians(1_000_000, 21, (-6.0, -4.5), (-3.0, 0.0));
    let gpu = gpu();
    if !binds_or_refused(&gpu, 12 * 1_000_000, || render(&gpu, &g.upload(&gpu)?, &cam, BG)) {
        return;
    }
    // With a million depths, a few pairs are a rounding apart, where the f32 and f64 depths
    // order apart and two Gaussians blend in swapped order.
    check_forward_pairs("1M tiny Gaussians", &g, &cam, 1e-8, 100);
}

#[test]
fn blending_follows_the_full_depth_at_1080p() {
    // 64 large, half-opaque Gaussians stacked 1e-5 apart in depth over the middle of a
    // 1920 x 1080 image, their indices in shuffled depth order, each its own colour. A sort key
    // that kept only the depth's top bits beside the tile (19 of them here) would tie them all
    // and blend in index order.
    let cam = camera(1920, 1080);
    let mut rng = Rng::new(81);
    let mut order: Vec<usize> = (0..64).collect();
    for i in (1..order.len()).rev() {
        order.swap(i, rng.below(i as u32 + 1) as usize);
    }
    let mut g = GaussianData::default();
    for &rank in &order {
        let z = 3.0 + rank as f32 * 1e-5;
        let mean = [rng.range(-0.05, 0.05) as f32, rng.range(-0.05, 0.05) as f32, z];
        let colour = [0; 3].map(|_| rng.uniform() as f32);
        g.push(mean, [-2.3, -2.4, -2.2], [1.0, 0.0, 0.0, 0.0], 0.0, colour);
    }
    let gpu = gpu();
    if !binds_or_refused(&gpu, 1920 * 1080 * 3 * 4, || render(&gpu, &g.upload(&gpu)?, &cam, BG)) {
        return;
    }
    let f = check_forward("64 Gaussians 1e-5 apart at 1080p", &g, &cam, 1e-12);
    let rgb: Vec<f32> = f.rendered.image.rgb.read().unwrap();
    let worst = rgb.iter().zip(&f.reference.rgb).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-5, "largest colour error {worst}");
    // The test can fail: blended in index order, the image is another.
    let mut ties = reference::Scene::from_data(&g);
    for (i, z) in ties.means.iter_mut().skip(2).step_by(3).enumerate() {
        *z = 3.0 + i as f64 * 1e-12;
    }
    let index_order = reference::render(&ties, &cam, BG);
    let moved = index_order.rgb.iter().zip(&f.reference.rgb).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(moved > 0.05, "index order changes colours by at most {moved}");
}

#[test]
fn negative_colours_clamp_to_zero() {
    // As 3D Gaussian splatting clamps its spherical-harmonic colour: a channel below zero draws
    // as zero and passes no gradient.
    let cam = camera(48, 40);
    let mut g = random_gaussians(60, 91, (-2.5, -1.5), (-1.0, 2.0));
    for c in g.colours.iter_mut().step_by(2) {
        *c = -1.5 * *c - 0.01;
    }
    let f = check_forward("negative colours", &g, &cam, 1e-11);
    let rgb: Vec<f32> = f.rendered.image.rgb.read().unwrap();
    let floor = BG.iter().fold(f32::INFINITY, |a, &b| a.min(b));
    assert!(rgb.iter().all(|&v| v >= 0.0), "a pixel went below zero");
    assert!(rgb.iter().any(|&v| v < floor), "the scene darkens no pixel below the background");
    check_backward("negative colours", &g, &cam, &f, 92, 1e-10);
}

#[test]
fn stress_one_gaussian_covering_the_image() {
    let cam = camera(80, 70);
    let mut g = GaussianData::default();
    g.push([0.1, -0.05, 3.0], [1.5, 1.2, 0.3], [0.9, 0.1, 0.2, 0.3], 1.0, [0.8, 0.4, 0.2]);
    let f = check_forward("one Gaussian over the image", &g, &cam, 1e-12);
    let (tx, ty) = cam.tiles();
    assert_eq!(f.reference.intersections, (tx * ty) as usize);
    check_backward("one Gaussian over the image", &g, &cam, &f, 31, 1e-10);
}

#[test]
fn stress_thousands_stacked_in_one_tile() {
    // 3000 faint Gaussians over one 16x16 tile, at distinct depths: many batches per tile in
    // both passes, the transmittance spent part way.
    let cam = camera(48, 48);
    let mut rng = Rng::new(41);
    let mut g = GaussianData::default();
    for i in 0..3000 {
        let z = 2.0 + i as f32 * 1e-3;
        let mean = [rng.range(-0.05, 0.05) as f32 * z, rng.range(-0.05, 0.05) as f32 * z, z];
        g.push(mean, [-3.0, -3.2, -3.1], [1.0, 0.0, 0.0, 0.1], -4.0, [0.2, 0.7, 0.5]);
    }
    let f = check_forward("3000 stacked", &g, &cam, 1e-11);
    check_backward("3000 stacked", &g, &cam, &f, 42, 1e-10);
}

#[test]
fn stress_all_saturated() {
    // Opacity sigmoid(12): every alpha is clamped at ALPHA_MAX and pixels saturate at once.
    let cam = camera(64, 48);
    let g = random_gaussians(400, 51, (-2.5, -1.0), (12.0, 12.0));
    let f = check_forward("all saturated", &g, &cam, 1e-11);
    let alpha: Vec<f32> = f.rendered.image.alpha.read().unwrap();
    assert!(alpha.iter().any(|&a| a > 0.999), "some pixels saturate");
    // Opacity-logit gradients are about 1e-6 of the others here (sigmoid'(12)) and come
    // from pixels where o exp(-power) crosses ALPHA_MAX, where f32 and f64 may decide apart.
    // Measured on lavapipe: opacities 7.9e-5, every other gradient below 1e-12.
    check_backward("all saturated", &g, &cam, &f, 52, 1e-3);
}

#[test]
fn poison_inputs_are_dropped_and_counted() {
    let cam = camera(64, 48);
    let clean = random_gaussians(50, 61, (-3.0, -1.5), (-1.0, 2.0));
    let mut g = clean.clone();
    let ok = ([0.0, 0.0, 3.0], [-2.0; 3], [1.0, 0.0, 0.0, 0.0], 1.0, [0.5; 3]);
    let mut push = |m: [f32; 3], s: [f32; 3], q: [f32; 4], o: f32, c: [f32; 3]| g.push(m, s, q, o, c);
    push([f32::NAN, 0.0, 3.0], ok.1, ok.2, ok.3, ok.4);
    push(ok.0, [f32::INFINITY, -2.0, -2.0], ok.2, ok.3, ok.4);
    push(ok.0, [f32::NEG_INFINITY; 3], ok.2, ok.3, ok.4); // zero scale
    push(ok.0, ok.1, [0.0; 4], ok.3, ok.4); // zero quaternion
    push(ok.0, ok.1, [f32::NAN, 0.0, 0.0, 1.0], ok.3, ok.4);
    push(ok.0, ok.1, ok.2, f32::NAN, ok.4);
    push(ok.0, ok.1, ok.2, ok.3, [0.5, f32::INFINITY, 0.5]);
    push([3e38, 0.0, 3.0], ok.1, ok.2, ok.3, ok.4); // finite, but overflows in projection
    push(ok.0, [40.0; 3], ok.2, ok.3, ok.4); // covariance overflows f32
                                             // Dropped for ordinary reasons.
    push([0.0, 0.0, -3.0], ok.1, ok.2, ok.3, ok.4); // behind the camera
    push([0.0, 0.0, 0.005], ok.1, ok.2, ok.3, ok.4); // before the near plane
    push([50.0, 0.0, 3.0], ok.1, ok.2, ok.3, ok.4); // outside the image
    push(ok.0, ok.1, ok.2, -9.0, ok.4); // opacity below 1/255
    let f = check_forward("poison", &g, &cam, 1e-11);
    let stats = f.rendered.stats().unwrap();
    assert_eq!(stats.invalid, 9, "{stats:?}");
    assert_eq!(stats.behind_near_plane, 2, "{stats:?}");
    assert_eq!(stats.outside_image, 1, "{stats:?}");
    assert_eq!(stats.too_faint, 1, "{stats:?}");
    // The poisoned scene renders exactly like the clean one.
    let clean_ref = reference::render(&reference::Scene::from_data(&clean), &cam, BG);
    assert_eq!(f.reference.rgb, clean_ref.rgb);
    // Gradients are finite, and zero for every dropped Gaussian.
    let gpu = gpu();
    let (dr, da, dd) = image_grads(&cam, 62);
    let t = |v: &[f32], s: &[usize]| Tensor::from_slice(&gpu, s, v).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let grads = raster::render_backward(
        &mut rec,
        &f.gaussians,
        &f.rendered,
        &t(&dr, &[48, 64, 3]),
        &t(&da, &[48, 64]),
        &t(&dd, &[48, 64]),
    )
    .unwrap();
    rec.submit().unwrap();
    for (name, (got, width)) in NAMES.iter().zip(read_grads(&grads).iter().zip([3, 3, 4, 1, 3])) {
        assert!(got.iter().all(|v| v.is_finite()), "d{name} has a non-finite value");
        assert!(got[50 * width..].iter().all(|&v| v == 0.0), "d{name} of a dropped Gaussian");
    }
}

/// A 32 x 32 pinhole camera at the origin looking down +z, focal length 40 px, principal
/// point at the image centre: written out here, not through the engine's constructors.
fn pinhole() -> Camera {
    Camera {
        width: 32,
        height: 32,
        fx: 40.0,
        fy: 40.0,
        cx: 16.0,
        cy: 16.0,
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [0.0; 3],
    }
}

/// The opacity of a Gaussian whose projected covariance (pixels^2, before the 0.3 px^2
/// low-pass) is `cov` = [a, b; b, c], centred at (`u`, `v`), at the centre of pixel (x, y),
/// by the textbook formulas: alpha = min(0.99, o exp(-d^T S^-1 d / 2)), 0 below 1/255.
fn closed_form_alpha(o: f64, (u, v): (f64, f64), [a, b, c]: [f64; 3], x: usize, y: usize) -> f64 {
    let (a, c) = (a + 0.3, c + 0.3);
    let det = a * c - b * b;
    let (dx, dy) = (x as f64 + 0.5 - u, y as f64 + 0.5 - v);
    let power = (c * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (2.0 * det);
    let alpha = (o * (-power).exp()).min(0.99);
    if alpha < 1.0 / 255.0 {
        0.0
    } else {
        alpha
    }
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// One isotropic Gaussian off the axis, written with its closed form: its image-plane
/// covariance is `s^2 J J^T`, J the pinhole's Jacobian at the mean (`(f/z)^2 [1 + x^2/z^2,
/// x y/z^2; x y/z^2, 1 + y^2/z^2]` times `s^2`); every pixel's colour, alpha and depth
/// follow, the footprint is exactly the pixels where alpha reaches 1/255 (all others show the
/// background), and the centre pixel has the opacity times the colour. Independent of the
/// rasteriser's reference: it would catch a convention both share (pixel centres, the
/// Jacobian's sign, the blend of one Gaussian with the background).
#[test]
fn one_gaussian_is_its_closed_form() {
    let gpu = gpu();
    let cam = pinhole();
    let (x, y, z, s, logit) = (0.05f64, -0.35f64, 4.0f64, 0.12f64, 0.8f64);
    let colour = [0.9f32, 0.4, 0.2];
    let mut g = GaussianData::default();
    g.push([x, y, z].map(|v| v as f32), [s.ln() as f32; 3], [0.3, -0.5, 0.1, 0.7], logit as f32, colour);
    let out = render(&gpu, &g.upload(&gpu).unwrap(), &cam, BG).unwrap();
    let (rgb, alpha, depth): (Vec<f32>, Vec<f32>, Vec<f32>) =
        (out.image.rgb.read().unwrap(), out.image.alpha.read().unwrap(), out.image.depth.read().unwrap());
    let f = 40.0;
    let k = s * s * (f / z) * (f / z);
    let cov = [k * (1.0 + x * x / (z * z)), k * x * y / (z * z), k * (1.0 + y * y / (z * z))];
    let centre = (f * x / z + 16.0, f * y / z + 16.0);
    assert_eq!(centre, (16.5, 12.5), "the mean projects to the centre of pixel (16, 12)");
    let o = sigmoid(logit);
    let (mut covered, mut worst) = (0, 0f64);
    for py in 0..32 {
        for px in 0..32 {
            let a = closed_form_alpha(o, centre, cov, px, py);
            covered += (a > 0.0) as usize;
            let i = py * 32 + px;
            let mut errs = vec![(alpha[i] as f64 - a).abs(), (depth[i] as f64 - z * a).abs()];
            for ch in 0..3 {
                let want = colour[ch] as f64 * a + BG[ch] as f64 * (1.0 - a);
                errs.push((rgb[3 * i + ch] as f64 - want).abs());
            }
            let e = errs.iter().fold(0f64, |m, &e| m.max(e));
            worst = worst.max(e);
            assert!(e < 1e-5, "pixel ({px}, {py}): alpha {} against {a}", alpha[i]);
        }
    }
    if verbose() {
        eprintln!(
            "one Gaussian: {covered} pixels covered, worst difference from the closed form {worst:.2e}"
        );
    }
    let c = 12 * 32 + 16;
    assert!((alpha[c] as f64 - o).abs() < 1e-6, "centre alpha {} against the opacity {o}", alpha[c]);
    assert!(covered > 50 && covered < 32 * 32, "{covered} pixels covered");
}

/// A Gaussian stretched along x (scales 0.2, 0.05, 0.05) turned a quarter turn about z by the
/// quaternion (w, x, y, z) = (cos 45, 0, 0, sin 45): on the axis its footprint is
/// `(f/z)^2 diag(0.05^2, 0.2^2)`, tall and narrow. A rasteriser reading the quaternion as
/// (x, y, z, w) would turn it about x instead and draw it wide.
#[test]
fn a_turned_gaussian_is_its_closed_form() {
    let gpu = gpu();
    let cam = pinhole();
    let z = 5.0f64;
    let h = std::f32::consts::FRAC_1_SQRT_2;
    let mut g = GaussianData::default();
    g.push([0.0, 0.0, z as f32], [0.2f32.ln(), 0.05f32.ln(), 0.05f32.ln()], [h, 0.0, 0.0, h], 2.0, [1.0; 3]);
    let out = render(&gpu, &g.upload(&gpu).unwrap(), &cam, [0.0; 3]).unwrap();
    let alpha: Vec<f32> = out.image.alpha.read().unwrap();
    let k = (40.0 / z) * (40.0 / z);
    let cov = [k * 0.05 * 0.05, 0.0, k * 0.2 * 0.2];
    for py in 0..32 {
        for px in 0..32 {
            let a = closed_form_alpha(sigmoid(2.0), (16.0, 16.0), cov, px, py);
            let got = alpha[py * 32 + px] as f64;
            assert!((got - a).abs() < 1e-5, "pixel ({px}, {py}): alpha {got} against {a}");
        }
    }
    // Tall: 2.5 pixels above the centre still well covered, 3.5 to its side not at all.
    assert!(alpha[13 * 32 + 16] > 0.2 && alpha[16 * 32 + 19] == 0.0);
}

/// Two Gaussians on one line of sight, the far one listed first: the near one blends first,
/// C = c1 a1 + c2 a2 (1 - a1) + bg (1 - a1)(1 - a2), A = 1 - (1 - a1)(1 - a2), and
/// D = z1 a1 + z2 a2 (1 - a1), with each alpha from its closed form.
#[test]
fn two_gaussians_blend_front_to_back_by_depth() {
    let gpu = gpu();
    let cam = pinhole();
    let (near, far) = ((3.0f64, 0.1f64, 0.3f64), (6.0f64, 0.2f64, 1.2f64)); // (z, scale, logit)
    let (c_near, c_far) = ([1.0f32, 0.0, 0.0], [0.0f32, 1.0, 0.0]);
    let mut g = GaussianData::default();
    for ((z, s, l), c) in [(far, c_far), (near, c_near)] {
        g.push([0.0, 0.0, z as f32], [(s as f32).ln(); 3], [1.0, 0.0, 0.0, 0.0], l as f32, c);
    }
    let out = render(&gpu, &g.upload(&gpu).unwrap(), &cam, BG).unwrap();
    let (rgb, alpha, depth): (Vec<f32>, Vec<f32>, Vec<f32>) =
        (out.image.rgb.read().unwrap(), out.image.alpha.read().unwrap(), out.image.depth.read().unwrap());
    let alpha_of = |(z, s, l): (f64, f64, f64), px, py| {
        let k = s * s * (40.0 / z) * (40.0 / z);
        closed_form_alpha(sigmoid(l), (16.0, 16.0), [k, 0.0, k], px, py)
    };
    for (px, py) in [(15, 15), (16, 16), (17, 15), (14, 17), (16, 18)] {
        let (a1, a2) = (alpha_of(near, px, py), alpha_of(far, px, py));
        let i = py * 32 + px;
        for ch in 0..3 {
            let want = c_near[ch] as f64 * a1
                + c_far[ch] as f64 * a2 * (1.0 - a1)
                + BG[ch] as f64 * (1.0 - a1) * (1.0 - a2);
            assert!((rgb[3 * i + ch] as f64 - want).abs() < 1e-5, "pixel ({px}, {py}) channel {ch}");
        }
        assert!((alpha[i] as f64 - (1.0 - (1.0 - a1) * (1.0 - a2))).abs() < 1e-5, "alpha at ({px}, {py})");
        assert!(
            (depth[i] as f64 - (near.0 * a1 + far.0 * a2 * (1.0 - a1))).abs() < 1e-5,
            "depth at ({px}, {py})"
        );
        assert!(a1 > 0.0 && a2 > 0.0, "both Gaussians reach ({px}, {py})");
    }
}

/// Every buffer of a forward pass, as bits, the tile lists up to `pairs` entries.
fn forward_bits(img: &Image, pairs: usize) -> Vec<Vec<u32>> {
    let bits = |t: &Tensor| -> Vec<u32> { t.read::<f32>().unwrap().iter().map(|v| v.to_bits()).collect() };
    let words = |t: &Tensor, n: usize| -> Vec<u32> { t.read::<u32>().unwrap()[..n].to_vec() };
    vec![
        bits(&img.rgb),
        bits(&img.alpha),
        bits(&img.depth),
        bits(&img.final_t),
        words(&img.last, img.last.numel()),
        words(&img.ranges, img.ranges.numel()),
        words(&img.ids, pairs),
        words(&img.slots, pairs),
    ]
}

#[test]
fn lists_sized_ahead_give_the_same_bits_and_drop_what_overflows() {
    // A training step records the rasterisation with the projection, into tile lists sized
    // from earlier steps: within that room, every bit of the forward and backward passes is
    // the exactly sized pass's; past it, pairs are dropped without a write out of bounds, and
    // the step's update is vetoed on the device. 64x64 has 16 tiles, whose last one's masked
    // key is the unused entries' (they stay behind it by the sort's stability); 64x48 has 12.
    let gpu = gpu();
    for (w, h, n) in [(64, 48, 300), (64, 64, 400)] {
        let cam = camera(w, h);
        let what = format!("{n} Gaussians {w}x{h}");
        let g = random_gaussians(n, 7 + n as u64, (-3.5, -1.5), (-2.0, 2.0));
        let gaussians = g.upload(&gpu).unwrap();
        let exact = render(&gpu, &gaussians, &cam, BG).unwrap();
        let pairs = exact.projected.intersections().unwrap();
        assert!(pairs > 300, "{what}: {pairs} pairs");
        let (dr, da, dd) = image_grads(&cam, 5);
        let (hh, ww) = (h as usize, w as usize);
        let t_dr = Tensor::from_slice(&gpu, &[hh, ww, 3], &dr).unwrap();
        let t_da = Tensor::from_slice(&gpu, &[hh, ww], &da).unwrap();
        let t_dd = Tensor::from_slice(&gpu, &[hh, ww], &dd).unwrap();
        let backward = |r: &Rendered| -> Vec<Vec<f32>> {
            let mut rec = gpu.recorder().unwrap();
            let d =
                render_backward_with(&mut rec, BackwardKernel::Ordered, &gaussians, r, &t_dr, &t_da, &t_dd)
                    .unwrap();
            rec.submit().unwrap();
            read_grads(&d).to_vec()
        };
        let want = (forward_bits(&exact.image, pairs), backward(&exact));
        // Room just enough, and room past one sort block (4096 pairs): several blocks of
        // unused entries behind the pairs.
        for room in [pairs, pairs + 5000] {
            let mut rec = gpu.recorder().unwrap();
            let projected = raster::project(&mut rec, &gaussians, &cam).unwrap();
            let image = raster::rasterize_within(&mut rec, &projected, room, BG).unwrap();
            rec.submit().unwrap();
            assert_eq!(projected.intersections().unwrap(), pairs);
            assert_eq!(image.room, room);
            let r = Rendered { projected, image };
            assert!(forward_bits(&r.image, pairs) == want.0, "{what}, room {room}: the forward pass's bits");
            let got = backward(&r);
            let same = got
                .iter()
                .zip(&want.1)
                .all(|(a, b)| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits()));
            assert!(same, "{what}, room {room}: the backward pass's bits");
        }

        // Half the room: the pass runs and stays finite, the count says it overflowed, and the
        // veto turns a norm to +Inf only where the count is past the limit.
        let room = pairs / 2;
        let mut rec = gpu.recorder().unwrap();
        let projected = raster::project(&mut rec, &gaussians, &cam).unwrap();
        let image = raster::rasterize_within(&mut rec, &projected, room, BG).unwrap();
        let norms = [[1.5f32, 2.25], [3.0, 9.0]].map(|v| Tensor::from_slice(&gpu, &[2], &v).unwrap());
        veto_if_over(&mut rec, projected.pairs(), room as u32, &norms[0]).unwrap();
        veto_if_over(&mut rec, projected.pairs(), pairs as u32, &norms[1]).unwrap();
        rec.submit().unwrap();
        assert_eq!(projected.intersections().unwrap(), pairs);
        let r = Rendered { projected, image };
        let rgb: Vec<f32> = r.image.rgb.read().unwrap();
        assert!(rgb.iter().all(|v| v.is_finite()), "{what}: an overflowed pass drew a non-finite pixel");
        assert!(backward(&r).iter().flatten().all(|v| v.is_finite()), "{what}: overflowed backward");
        assert_eq!(norms[0].read::<f32>().unwrap(), vec![f32::INFINITY, 2.25], "{what}: vetoed");
        assert_eq!(norms[1].read::<f32>().unwrap(), vec![3.0, 9.0], "{what}: within the limit");
    }
}

#[test]
fn bad_shapes_and_cameras_are_errors() {
    let gpu = gpu();
    let g = random_gaussians(3, 71, (-2.0, -1.0), (0.0, 1.0));
    let mut bad = g.clone();
    bad.quats.pop();
    let e = bad.upload(&gpu).err().unwrap().to_string();
    assert!(e.contains("quat"), "{e}");
    let t = g.upload(&gpu).unwrap();
    let mut cam = camera(0, 10);
    let e = render(&gpu, &t, &cam, BG).err().unwrap().to_string();
    assert!(e.contains("0x10") && e.contains("non-zero"), "{e}");
    cam = camera(10, 10);
    cam.fx = f32::NAN;
    let e = render(&gpu, &t, &cam, BG).err().unwrap().to_string();
    assert!(e.contains("fx"), "{e}");
    let _ = raster::TILE;
}

#[test]
fn spherical_harmonics_colour_each_gaussian_along_its_view() {
    // The colour each Gaussian shows from a camera centre, degrees 1 to 3, against the f64
    // reference (which velox view's shader and velox_io share), before the rasteriser's clamp;
    // a mean at the centre keeps its degree-0 colour.
    let gpu = gpu();
    let mut rng = Rng::new(31);
    let n = 300;
    let eye = [1.5f32, -0.5, 2.5];
    let mut means = rng.uniform_vec(3 * n, -1.0, 1.0);
    means[..3].copy_from_slice(&eye);
    let colours = rng.uniform_vec(3 * n, -0.2, 1.2);
    let t = |x: &[f32], w: usize| Tensor::from_slice(&gpu, &[x.len() / w, w], x).unwrap();
    let ones = vec![0.0; 3 * n];
    let g = Gaussians {
        means: t(&means, 3),
        log_scales: t(&ones, 3),
        quats: t(&vec![1.0; 4 * n], 4),
        opacities: t(&vec![0.0; n], 1),
        colours: t(&colours, 3),
    };
    for degree in 1..=3 {
        let k = raster::sh::per_channel(degree);
        let rest = rng.uniform_vec(3 * k * n, -0.5, 0.5);
        let mut rec = gpu.recorder().unwrap();
        let got = raster::sh_colours(&mut rec, &g, &t(&rest, 3 * k), degree, eye).unwrap();
        rec.submit().unwrap();
        let got: Vec<f32> = got.read().unwrap();
        let mut worst = 0.0f64;
        for i in 0..n {
            let d: [f64; 3] = std::array::from_fn(|a| (means[3 * i + a] - eye[a]) as f64);
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let base = [0, 1, 2].map(|c| colours[3 * i + c]);
            let want = if l == 0.0 {
                base.map(|c| (c as f64).max(0.0))
            } else {
                reference::sh_colour(base, &rest[i * 3 * k..(i + 1) * 3 * k], degree, d.map(|v| v / l))
            };
            for c in 0..3 {
                worst = worst.max(((got[3 * i + c] as f64).max(0.0) - want[c]).abs());
            }
        }
        eprintln!("degree {degree}: max abs err {worst:.2e}");
        assert!(worst <= 1e-5, "degree {degree}: max abs err {worst:.3e}");
    }
    // Bad requests are refused with what is wrong.
    let mut rec = gpu.recorder().unwrap();
    let rest = t(&vec![0.0; 9 * n], 9);
    let err = raster::sh_colours(&mut rec, &g, &rest, 4, eye).unwrap_err().to_string();
    assert!(err.contains("degree 4"), "{err}");
    let err = raster::sh_colours(&mut rec, &g, &rest, 2, eye).unwrap_err().to_string();
    assert!(err.contains("harmonics") && err.contains("24"), "{err}");
    let err = raster::sh_colours(&mut rec, &g, &rest, 1, [f32::NAN, 0.0, 0.0]).unwrap_err().to_string();
    assert!(err.contains("not finite"), "{err}");
}
