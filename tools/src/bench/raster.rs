//! `velox bench raster`: the Gaussian rasteriser's forward and forward + backward GPU time
//! against the number of Gaussians and the resolution, on the scene gsplat is compared on
//! ([`GaussianData::benchmark_scene`]: camera at the origin, fov 50 deg, loss = sum of the
//! image), and its error against the f64 reference.
//!
//! The forward pass is two recordings (projection and scan; then keys, sort, ranges, blend),
//! the backward one; each is timed with GPU timestamps and the median of their sum over the
//! repeats is reported. The backward pass is timed with both of its kernels: the deterministic
//! one that training uses (per-pair sums in a fixed order) and the fastest one, whose atomic
//! adds vary in their last bits between runs. The forward error is measured on 4096 sampled
//! pixels (the reference is a CPU loop); the backward error over every gradient on a small
//! case.

use velox_engine::ops::raster::{
    self, project, rasterize, reference, render, render_backward_with, BackwardKernel, Camera, GaussianData,
    TILE,
};
use velox_engine::rng::Rng;
use velox_engine::stats::{max_abs_err, nmse};
use velox_engine::{Gpu, Recorder, Result, Tensor};

use super::{print_header, print_row, Record, Roof, SizeSet};

/// gsplat 1.5.3 on an H100, same scene at 1920 x 1080 (issue 4): (Gaussians, forward ms,
/// forward + backward ms).
pub const GSPLAT_H100: [(usize, f64, f64); 2] = [(1_000_000, 2.27, 4.83), (3_000_000, 5.12, 9.55)];

struct Sizes {
    /// Gaussian counts at `count_res`.
    counts: Vec<usize>,
    count_res: (u32, u32),
    /// Resolutions at `res_count` Gaussians.
    resolutions: Vec<(u32, u32)>,
    res_count: usize,
}

fn sizes(set: SizeSet) -> Sizes {
    if set.small() {
        Sizes {
            counts: vec![10_000, 100_000],
            count_res: (640, 360),
            resolutions: vec![(256, 256), (640, 360)],
            res_count: 30_000,
        }
    } else {
        Sizes {
            counts: vec![10_000, 100_000, 1_000_000, 3_000_000, 10_000_000],
            count_res: (1920, 1080),
            resolutions: vec![(256, 256), (512, 512), (1280, 720), (1920, 1080)],
            res_count: 1_000_000,
        }
    }
}

/// Runs `f` in its own recording between two timestamps; GPU ms (wall ms without timestamps).
fn timed<T>(gpu: &Gpu, f: impl FnOnce(&mut Recorder) -> Result<T>) -> Result<(T, f64, bool)> {
    let mut rec = gpu.recorder()?;
    let t0 = rec.timestamp();
    let out = f(&mut rec)?;
    let t1 = rec.timestamp();
    let wall = std::time::Instant::now();
    let done = rec.submit()?;
    Ok(match (t0, t1) {
        (Some(a), Some(b)) => (out, (done.timestamps_ns[b] - done.timestamps_ns[a]) / 1e6, true),
        _ => (out, wall.elapsed().as_secs_f64() * 1e3, false),
    })
}

struct Timing {
    forward: (f64, f64),
    /// Per backward kernel of [`kernels`].
    forward_backward: Vec<(f64, f64)>,
    gpu_timed: bool,
    pairs: usize,
}

/// The backward kernels timed: the deterministic one, and the device's fastest.
fn kernels(gpu: &Gpu) -> [BackwardKernel; 2] {
    [BackwardKernel::Ordered, BackwardKernel::fastest(gpu)]
}

fn kernel_name(k: BackwardKernel) -> &'static str {
    match k {
        BackwardKernel::Ordered => "ordered",
        BackwardKernel::Atomic => "atomic",
        BackwardKernel::CompareAndSwap => "cas",
    }
}

fn median_min(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    (v[v.len() / 2], v[0])
}

fn time_case(gpu: &Gpu, g: &GaussianData, cam: &Camera, repeats: u32) -> Result<Timing> {
    let t = g.upload(gpu)?;
    let px = (cam.width * cam.height) as usize;
    // Loss = sum of the image: dL/drgb = 1, nothing on alpha and depth.
    let ones = Tensor::from_slice(gpu, &[cam.height as usize, cam.width as usize, 3], &vec![1.0f32; 3 * px])?;
    let zeros = Tensor::from_slice(gpu, &[cam.height as usize, cam.width as usize], &vec![0.0f32; px])?;
    let (mut fwd, mut all) = (Vec::new(), vec![Vec::new(); 2]);
    let mut gpu_timed = true;
    let mut pairs = 0;
    for i in 0..=repeats {
        let (p, t_project, a) = timed(gpu, |rec| project(rec, &t, cam))?;
        pairs = p.intersections()?;
        let (image, t_raster, b) = timed(gpu, |rec| rasterize(rec, &p, [0.0; 3]))?;
        let r = raster::Rendered { projected: p, image };
        gpu_timed &= a && b;
        for (k, times) in kernels(gpu).into_iter().zip(&mut all) {
            let (_, t_back, c) =
                timed(gpu, |rec| render_backward_with(rec, k, &t, &r, &ones, &zeros, &zeros))?;
            gpu_timed &= c;
            if i > 0 {
                times.push(t_project + t_raster + t_back);
            }
        }
        if i > 0 {
            fwd.push(t_project + t_raster);
        }
    }
    let forward_backward = all.into_iter().map(median_min).collect();
    Ok(Timing { forward: median_min(fwd), forward_backward, gpu_timed, pairs })
}

/// Forward error on `samples` random pixels.
fn forward_error(gpu: &Gpu, g: &GaussianData, cam: &Camera, samples: usize) -> Result<(f64, f64, usize)> {
    let t = g.upload(gpu)?;
    let r = render(gpu, &t, cam, [0.0; 3])?;
    let rgb: Vec<f32> = r.image.rgb.read()?;
    let mut rng = Rng::new(5);
    let all = (cam.width * cam.height) as usize;
    let pixels: Vec<(u32, u32)> = if all <= samples {
        (0..all as u32).map(|i| (i % cam.width, i / cam.width)).collect()
    } else {
        (0..samples).map(|_| (rng.below(cam.width), rng.below(cam.height))).collect()
    };
    let want = reference::render_pixels(&reference::Scene::from_data(g), cam, [0.0; 3], &pixels);
    let mut have = Vec::new();
    let mut wanted = Vec::new();
    for (&(x, y), w) in pixels.iter().zip(&want) {
        let p = (y * cam.width + x) as usize;
        have.extend_from_slice(&rgb[3 * p..3 * p + 3]);
        wanted.extend_from_slice(&w.0);
    }
    Ok((nmse(&have, &wanted), max_abs_err(&have, &wanted), pixels.len()))
}

pub fn run(gpu: &Gpu, set: SizeSet, repeats: u32) -> Result<Vec<Record>> {
    let s = sizes(set);
    let c = gpu.caps();
    let device = c.name.clone();
    println!("device: {device} ({}); {repeats} timed repeats per case, median shown", c.kind);
    for k in kernels(gpu) {
        let how = k.check(gpu).map(|()| k.describe()).unwrap_or("unsupported on this device");
        println!("backward ({}): {how}", kernel_name(k));
    }
    print_header();
    let mut out = Vec::new();
    let mut cases: Vec<(usize, (u32, u32))> = s.counts.iter().map(|&n| (n, s.count_res)).collect();
    cases.extend(s.resolutions.iter().filter(|&&r| r != s.count_res).map(|&r| (s.res_count, r)));
    for (n, (w, h)) in cases {
        let g = GaussianData::benchmark_scene(n, 1);
        let cam = Camera::identity(50.0, w, h);
        let timing = time_case(gpu, &g, &cam, repeats)?;
        let (e, m, sampled) = forward_error(gpu, &g, &cam, 4096)?;
        let shape = format!("{n} gaussians {w}x{h}");
        // (name, times, whether the backward ran too)
        let mut rows = vec![("raster forward".to_string(), timing.forward, false)];
        for (k, t) in kernels(gpu).into_iter().zip(&timing.forward_backward) {
            rows.push((format!("raster fwd+bwd {}", kernel_name(k)), *t, true));
        }
        for (name, (median, min), backward) in rows {
            let rate = n as f64 / (median * 1e-3) / 1e6;
            let over = format!("forward rgb on {sampled} sampled pixels; {} tile pairs", timing.pairs);
            let t = (median, min, timing.gpu_timed);
            let (flops, bytes) = raster_work(n, w, h, timing.pairs, backward);
            let r = Record::timed(name, shape.clone(), "f32", &device, t, repeats, rate, "MGauss/s")
                .error(e, m, over)
                .work(flops, bytes, Roof::of(gpu.caps(), false));
            print_row(&r);
            out.push(r);
        }
    }
    for k in kernels(gpu) {
        let r = backward_error(gpu, k, repeats, &device)?;
        print_row(&r);
        out.push(r);
    }
    println!("gsplat 1.5.3 on an H100, same scenes at 1920x1080 (forward, forward+backward ms):");
    for (n, f, fb) in GSPLAT_H100 {
        println!("  {n} Gaussians: {f} ms, {fb} ms");
    }
    Ok(out)
}

/// The backward pass with `kernel` against the f64 reference on a small case, over every
/// gradient.
fn backward_error(gpu: &Gpu, kernel: BackwardKernel, repeats: u32, device: &str) -> Result<Record> {
    let (n, w, h) = (2000, 128, 96);
    let g = GaussianData::benchmark_scene(n, 2);
    let cam = Camera::identity(50.0, w, h);
    let t = g.upload(gpu)?;
    let px = (w * h) as usize;
    let ones = Tensor::from_slice(gpu, &[h as usize, w as usize, 3], &vec![1.0f32; 3 * px])?;
    let zeros = Tensor::from_slice(gpu, &[h as usize, w as usize], &vec![0.0f32; px])?;
    let r = render(gpu, &t, &cam, [0.0; 3])?;
    let mut times = Vec::new();
    let mut grads = None;
    let mut gpu_timed = true;
    for _ in 0..=repeats {
        let (gr, ms, timed_on_gpu) =
            timed(gpu, |rec| render_backward_with(rec, kernel, &t, &r, &ones, &zeros, &zeros))?;
        times.push(ms);
        gpu_timed &= timed_on_gpu;
        grads = Some(gr);
    }
    times.remove(0);
    let (median, min) = median_min(times);
    let grads = grads.expect("at least one run");
    let want = reference::render_backward(
        &reference::Scene::from_data(&g),
        &cam,
        [0.0; 3],
        &vec![1.0; 3 * px],
        &vec![0.0; px],
        &vec![0.0; px],
    );
    let mut have = Vec::new();
    let mut wanted = Vec::new();
    for (t, w) in [
        (&grads.means, &want.means),
        (&grads.log_scales, &want.log_scales),
        (&grads.quats, &want.quats),
        (&grads.opacities, &want.opacities),
        (&grads.colours, &want.colours),
    ] {
        have.extend(t.read::<f32>()?);
        wanted.extend_from_slice(w);
    }
    let rate = n as f64 / (median * 1e-3) / 1e6;
    let t = (median, min, gpu_timed);
    let r = Record::timed(
        format!("raster backward {}", kernel_name(kernel)),
        format!("{n} gaussians {w}x{h}"),
        "f32",
        device,
        t,
        repeats,
        rate,
        "MGauss/s",
    );
    Ok(r.against(&have, &wanted, "every parameter gradient, loss = sum of the image"))
}

/// A render's work, for the roofline columns: about 120 FLOPs to project a Gaussian and 15 for
/// each of the 256 pixels of each (tile, Gaussian) pair it blends into (the conic, an exp, the
/// blend), twice that backward; its compulsory bytes are the Gaussians' 14 f32 parameters read
/// and an RGBA image written, and backward the parameters and the image gradient read and the
/// parameter gradients written.
fn raster_work(n: usize, w: u32, h: u32, pairs: usize, backward: bool) -> (f64, f64) {
    let (n, pixels, pairs) = (n as f64, (w as f64) * (h as f64), pairs as f64);
    let tile = (TILE * TILE) as f64;
    let forward = (120.0 * n + 15.0 * tile * pairs, 4.0 * (14.0 * n + 4.0 * pixels));
    if backward {
        (3.0 * forward.0, forward.1 + 4.0 * (28.0 * n + 4.0 * pixels))
    } else {
        forward
    }
}
