//! `velox bench models`: the Velox autoencoder's parts at the paper config with random weights
//! (the small config on CPU devices such as lavapipe, or with `--quick`), timed against the
//! paper's H100 figures (docs/models.md).
//!
//! - encoder: a random 4D cloud (points on a sphere whose radius changes over the 24 frames,
//!   random colours; 1.44 M points at the paper config) to k x 32 tokens, one recording timed
//!   by GPU timestamps;
//! - Gaussian decoder, one frame (all of the head's outputs): its queries are the occupied voxels of a sphere of radius 0.8
//!   at the config's grid, a realistic surface count: about 11.3k of 64^3 at the paper config
//!   (x 64 = 725k Gaussians), about 2.9k of 32^3 at the small one; the record's shape gives
//!   it. One recording timed by GPU timestamps;
//! - voxel decoder, one frame: the coarse stage over every cell and the fine stage over the
//!   cells of a sphere of radius 0.8 (about 500 of the 4096 at 16^3), one recording timed by
//!   GPU timestamps (the paper config of the voxel decoder; its small one on CPU devices);
//! - tracking network: 2048 queries' 24 positions from the tokens (the paper config's
//!   training draw; the paper's evaluation does not say how many), one recording timed by GPU
//!   timestamps (the small config's 512 on CPU devices);
//! - 4D surface decoder: sampling 16384 points with Heun, 20 and 100 steps (1024 points on a
//!   CPU device; 256 points and 4 and 20 steps with `--quick`), timed as the whole sampling
//!   call (one submission per step and chunk, so wall clock, `gpu_timed: false`);
//! - DINOv2 over a video's 24 frames (ViT-L/14 at 532 px at the paper config; a 2-block,
//!   128-wide one at 56 px on CPU devices), random weights, wall clock;
//! - generator: 20 Euler steps with guidance (the paper config with DINOv2 features; the small
//!   one on CPU devices), the condition's keys and values computed once, wall clock.
//!
//! Weights: the store's initialisation, with every parameter that starts at zero (adaLN-Zero
//! maps, output layers, biases) drawn from N(0, 0.02^2) instead, so that no path is a
//! constant.
//!
//! Each part runs in f32 and in f16 (matrix products and attention on f16 operands, f32
//! accumulation; `velox_engine::Precision`). The f16 record's error is its output against the
//! f32 path's on the same input (encoder: the tokens; Gaussian decoder: the means; surface
//! decoder: the sampled points). The f32 record's is the NMSE of its last timed run against
//! a first run (a determinism check: atomics may reorder sums); `error_over` says which.

use velox_engine::ops::columns::copy_columns;
use velox_engine::rng::Rng;
use velox_engine::stats::{max_abs_err, nmse};
use velox_engine::{Gpu, Precision, Result, Tensor};
use velox_io::cloud;
use velox_models::config::{AutoencoderConfig, GeneratorConfig, TrackerConfig, VoxelConfig};
use velox_models::params::{build, ParamStore};
use velox_models::velox::autoencoder::{tau_of, FRAMES};
use velox_models::velox::dinov2::{Dinov2, Dinov2Config, PATCH, PATCH_VALUES};
use velox_models::velox::encoder::Encoder;
use velox_models::velox::gaussians::{occupied_voxels, GaussianDecoder};
use velox_models::velox::generator::{Condition, GenerateSpec, Generator};
use velox_models::velox::surface::{SampleSpec, Sampler, SurfaceDecoder};
use velox_models::velox::tracker::Tracker;
use velox_models::velox::voxels::{cell_labels, VoxelDecoder, FRAME_WORDS};

use super::{print_header, print_row, time_gpu, Record, SizeSet};

/// The paper's H100 times in ms (docs/models.md): encoder, Gaussian decoder one frame, 4D surface
/// decoder 16384 points (the table does not give its steps).
const PAPER_H100_MS: [(&str, f64); 6] = [
    ("encoder, 1.44 M points -> 8192 tokens", 387.66),
    ("Gaussian decoder, one frame", 32.71),
    ("voxel decoder, one frame", 20.14),
    ("4D surface decoder, 16384 points", 24_800.0),
    ("tracking network (after encoding)", 19.65),
    ("video-to-4D, 20 Euler steps", 12_870.0),
];

const F32_ERROR_OVER: &str = "the f32 path's first run (determinism check of the last timed run)";
const F16_ERROR_OVER: &str = "the f32 path's output on the same input";
const PRECISIONS: [Precision; 2] = [Precision::F32, Precision::F16];

/// The error column of a record: f32 against its own first run, f16 against f32.
fn error_reference<'a>(
    p: Precision,
    f32_first: &'a [f32],
    own_first: &'a [f32],
) -> (&'a [f32], &'static str) {
    match p {
        Precision::F32 => (own_first, F32_ERROR_OVER),
        Precision::F16 => (f32_first, F16_ERROR_OVER),
    }
}

struct Sizes {
    cfg: AutoencoderConfig,
    points: usize,
    surface_points: usize,
    steps: [usize; 2],
}

fn sizes(set: SizeSet) -> Sizes {
    if set == SizeSet::Quick {
        // Seconds on lavapipe: fewer points and steps for the surface decoder.
        Sizes { cfg: AutoencoderConfig::small(), points: 24_000, surface_points: 256, steps: [4, 20] }
    } else if set == SizeSet::Small {
        Sizes { cfg: AutoencoderConfig::small(), points: 24_000, surface_points: 1024, steps: [20, 100] }
    } else {
        Sizes { cfg: AutoencoderConfig::paper(), points: 1_440_000, surface_points: 16384, steps: [20, 100] }
    }
}

/// Draws every parameter that starts at exactly zero from N(0, 0.02^2), and rounds the result
/// to the store's f16 copies.
fn liven(store: &ParamStore, rng: &mut Rng) -> Result<()> {
    let mut p: Vec<f32> = store.flat_params().read()?;
    for v in p.iter_mut().filter(|v| **v == 0.0) {
        *v = (0.02 * rng.normal()) as f32;
    }
    store.flat_params().write(&p)?;
    let mut rec = store.flat_params().gpu().recorder()?;
    store.sync_half(&mut rec)?;
    rec.submit()?;
    Ok(())
}

/// `n` points on a sphere of radius 0.6 to 0.8 (growing over the frames), frame-major, with
/// random colours: rows of (x, y, z, r, g, b, tau).
fn sphere_cloud(n: usize, rng: &mut Rng) -> Vec<f32> {
    let mut out = Vec::with_capacity(n * cloud::CHANNELS);
    for i in 0..n {
        let f = i * FRAMES / n;
        let r = 0.6 + 0.2 * f as f64 / (FRAMES - 1) as f64;
        let d = [rng.normal(), rng.normal(), rng.normal()];
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-9);
        out.extend(d.map(|v| (r * v / l) as f32));
        out.extend([rng.uniform() as f32, rng.uniform() as f32, rng.uniform() as f32, tau_of(f)]);
    }
    out
}

/// A precision's record figures: timing, NMSE, max abs error, what the error is against.
type PrecisionRun = (Precision, (f64, f64, bool), f64, f64, &'static str);

/// Times `run` (one recording) in f32 and in f16; errors as [`error_reference`] says.
fn both_precisions(
    gpu: &Gpu,
    repeats: u32,
    run: impl Fn(&mut velox_engine::Recorder, Precision) -> Result<Tensor>,
) -> Result<Vec<PrecisionRun>> {
    let mut f32_first = Vec::new();
    let mut out = Vec::new();
    for p in PRECISIONS {
        let (t, first, last) = timed_outputs(gpu, repeats, |rec| run(rec, p))?;
        if p == Precision::F32 {
            f32_first = first.clone();
        }
        let (reference, over) = error_reference(p, &f32_first, &first);
        let (e, m) = errors(reference, &last);
        out.push((p, t, e, m, over));
    }
    Ok(out)
}

/// A timing as `time_gpu` gives it (median ms, min ms, GPU-timed), the output of a first
/// untimed run, and the output of the last timed run.
type TimedOutputs = ((f64, f64, bool), Vec<f32>, Vec<f32>);

/// Times `f` (GPU timestamps) and returns its [`TimedOutputs`].
fn timed_outputs(
    gpu: &Gpu,
    repeats: u32,
    mut f: impl FnMut(&mut velox_engine::Recorder) -> Result<Tensor>,
) -> Result<TimedOutputs> {
    let mut rec = gpu.recorder()?;
    let first = f(&mut rec)?;
    rec.submit()?;
    let first: Vec<f32> = first.read()?;
    let mut last = None;
    let t = time_gpu(gpu, repeats, |rec| {
        last = Some(f(rec)?);
        Ok(())
    })?;
    let last: Vec<f32> = last.expect("time_gpu runs at least once").read()?;
    Ok((t, first, last))
}

/// Times `run` by the wall clock in f32 and in f16 (`repeats` runs after an untimed first, for
/// calls of many submissions); errors as [`error_reference`] says.
fn wall_clock_both(repeats: u32, run: impl Fn(Precision) -> Result<Vec<f32>>) -> Result<Vec<PrecisionRun>> {
    let mut f32_first = Vec::new();
    let mut out = Vec::new();
    for p in PRECISIONS {
        let first = run(p)?;
        if p == Precision::F32 {
            f32_first = first.clone();
        }
        let mut times = Vec::new();
        let mut last = Vec::new();
        for _ in 0..repeats {
            let t0 = std::time::Instant::now();
            last = run(p)?;
            times.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        let (reference, over) = error_reference(p, &f32_first, &first);
        let (e, m) = errors(reference, &last);
        out.push((p, (times[times.len() / 2], times[0], false), e, m, over));
    }
    Ok(out)
}

fn errors(first: &[f32], last: &[f32]) -> (f64, f64) {
    let reference: Vec<f64> = first.iter().map(|&v| v as f64).collect();
    (nmse(last, &reference), max_abs_err(last, &reference))
}

pub fn run(gpu: &Gpu, set: SizeSet, repeats: u32) -> Result<Vec<Record>> {
    let s = sizes(set);
    let cfg = &s.cfg;
    let device = gpu.caps().name.clone();
    let mut rng = Rng::new(11);
    println!(
        "device: {device} ({}); the {} autoencoder config with random weights; {repeats} timed repeats, median shown",
        gpu.caps().kind,
        cfg.name
    );
    print_header();
    let mut out = Vec::new();
    let mut push = |r: Record| {
        print_row(&r);
        out.push(r);
    };
    let record = |name: &str, shape: String, p: Precision, t: (f64, f64, bool), work: f64, unit: &str| {
        Record::timed(name, shape, p.name(), &device, t, repeats, work / (t.0 * 1e-3), unit)
    };

    // Encoder.
    {
        let (encoder, store) = build(gpu, 1, |p| Encoder::new(p, "encoder", &cfg.encoder))?;
        liven(&store, &mut rng)?;
        let cloud = cloud::upload(gpu, &sphere_cloud(s.points, &mut rng))?;
        let encode = |rec: &mut velox_engine::Recorder, p: Precision| {
            rec.set_precision(p);
            encoder.forward(rec, &cloud, &mut Rng::new(5)).map(|o| o.0)
        };
        let (k, d) = (cfg.encoder.tokens, cfg.encoder.token_dim);
        for (p, t, e, m, over) in both_precisions(gpu, repeats, encode)? {
            let shape = format!("{} points -> {k}x{d}", s.points);
            push(record("encoder", shape, p, t, s.points as f64 / 1e6, "Mpoint/s").error(e, m, over));
        }
    }

    // Gaussian decoder, one frame.
    {
        let g = &cfg.gaussians;
        let (decoder, store) =
            build(gpu, 2, |p| GaussianDecoder::new(p, "gaussians", g, cfg.encoder.token_dim))?;
        liven(&store, &mut rng)?;
        let k = cfg.encoder.tokens;
        let tokens =
            Tensor::from_slice(gpu, &[k, cfg.encoder.token_dim], &rng.normal_vec(k * cfg.encoder.token_dim))?;
        // A dense sample of a sphere of radius 0.8: its occupied voxels are the queries.
        let sphere: Vec<f32> = (0..200_000)
            .flat_map(|_| {
                let d = [rng.normal(), rng.normal(), rng.normal()];
                let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-9);
                let p = d.map(|v| (0.8 * v / l) as f32);
                [p[0], p[1], p[2], 0.5, 0.5, 0.5, 0.0]
            })
            .collect();
        let centres = occupied_voxels(&sphere, 0.0, g.grid);
        let v = centres.len() / 3;
        let c = Tensor::from_slice(gpu, &[v, 3], &centres)?;
        let n = v * g.gaussians_per_voxel;
        let decode = |rec: &mut velox_engine::Recorder, p: Precision| {
            rec.set_precision(p);
            let (h, _) = decoder.forward(rec, &tokens, &c, 0.0)?;
            // Every output of the head, side by side: the means alone would hide errors
            // behind their voxel centres.
            let parts = h.fields();
            let cols: usize = parts.iter().map(|t| t.numel() / n).sum();
            let all = Tensor::empty(gpu, &[n, cols], velox_engine::DType::F32)?;
            let mut at = 0;
            for t in parts {
                let w = t.numel() / n;
                copy_columns(rec, &t.reshape(&[n, w])?, 0, &all, at, w, 1.0)?;
                at += w;
            }
            Ok(all)
        };
        for (p, t, e, m, over) in both_precisions(gpu, repeats, decode)? {
            let shape = format!("{v} vox of {0}^3 -> {n} Gaussians", g.grid);
            push(record("gaussian decoder frame", shape, p, t, n as f64 / 1e6, "MGauss/s").error(e, m, over));
        }
    }

    // 4D surface decoder: full sampling runs.
    {
        let (_store, decoder) = {
            let (store, decoder) = SurfaceDecoder::standalone(gpu, &cfg.surface, cfg.encoder.token_dim, 3)?;
            liven(&store, &mut rng)?;
            (store, decoder)
        };
        let k = cfg.encoder.tokens;
        let tokens =
            Tensor::from_slice(gpu, &[k, cfg.encoder.token_dim], &rng.normal_vec(k * cfg.encoder.token_dim))?;
        for steps in s.steps {
            let sample = |p: Precision| -> Result<Vec<f32>> {
                let spec = SampleSpec {
                    points: s.surface_points,
                    steps,
                    sampler: Sampler::Heun,
                    seed: 9,
                    precision: p,
                };
                decoder.sample(&tokens, 0.1, &spec)?.read()
            };
            for (p, t, e, m, over) in wall_clock_both(repeats, sample)? {
                let flops = 2.0
                    * steps as f64
                    * SurfaceDecoder::forward_flops(&cfg.surface, cfg.encoder.token_dim, s.surface_points, k)
                        as f64;
                push(
                    record(
                        &format!("surface decoder heun {steps}"),
                        format!("{} points, {} evaluations", s.surface_points, 2 * steps),
                        p,
                        t,
                        flops / 1e12,
                        "TFLOP/s",
                    )
                    .error(e, m, over),
                );
            }
        }
    }

    // Voxel decoder, one frame: the coarse stage over every cell, the fine stage over the
    // cells of a sphere of radius 0.8 (what the coarse stage would choose for it), one
    // recording.
    {
        let mut vcfg = if cfg.name == "paper" { VoxelConfig::paper() } else { VoxelConfig::small() };
        vcfg.token_dim = cfg.encoder.token_dim;
        let decoder = VoxelDecoder::new(gpu, &vcfg, 4)?;
        liven(&decoder.store, &mut rng)?;
        let k = cfg.encoder.tokens;
        let tokens = Tensor::from_slice(gpu, &[k, vcfg.token_dim], &rng.normal_vec(k * vcfg.token_dim))?;
        let mut frame = vec![0u64; FRAME_WORDS];
        for _ in 0..200_000 {
            let d = [rng.normal(), rng.normal(), rng.normal()];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-9);
            let v = d.map(|x| (((0.8 * x / l + 1.0) * 32.0) as usize).min(63));
            let i = v[0] + 64 * (v[1] + 64 * v[2]);
            frame[i / 64] |= 1 << (i % 64);
        }
        let chosen: Vec<usize> =
            cell_labels(&frame, vcfg.cells).iter().enumerate().filter(|c| *c.1).map(|c| c.0).collect();
        let per_cell = vcfg.cell_side().pow(3);
        let decode = |rec: &mut velox_engine::Recorder, p: Precision| {
            rec.set_precision(p);
            let coarse = decoder.coarse_logits(rec, &tokens, &[0.1])?;
            let fine = decoder
                .fine_logits(rec, &tokens, &[0.1], std::slice::from_ref(&chosen))?
                .expect("cells chosen");
            let (nc, nf) = (coarse.numel(), fine.numel());
            let all = Tensor::empty(gpu, &[nc + nf], velox_engine::DType::F32)?;
            rec.copy_rows(&coarse.reshape(&[nc])?, 0, &all, 0, nc)?;
            rec.copy_rows(&fine.reshape(&[nf])?, 0, &all, nc, nf)?;
            Ok(all)
        };
        for (p, t, e, m, over) in both_precisions(gpu, repeats, decode)? {
            let cells = vcfg.cells.pow(3);
            let shape = format!("{cells} cells, {} refined x {per_cell}", chosen.len());
            let voxels = (chosen.len() * per_cell) as f64;
            push(record("voxel decoder frame", shape, p, t, voxels / 1e6, "Mvoxel/s").error(e, m, over));
        }
        println!(
            "voxel decoder ({} config, {:.1} M parameters): the fine stage refines {} of {} cells; over every \
             cell it would do {:.1}x its work",
            vcfg.name,
            decoder.store.num_parameters() as f64 / 1e6,
            chosen.len(),
            vcfg.cells.pow(3),
            vcfg.cells.pow(3) as f64 / chosen.len() as f64
        );
    }

    // Tracking network: every query's 24 positions from the tokens, one recording; the
    // paper's evaluation does not say how many queries, so the paper config's training draw.
    {
        let mut tcfg = if cfg.name == "paper" { TrackerConfig::paper() } else { TrackerConfig::small() };
        tcfg.token_dim = cfg.encoder.token_dim;
        let tracker = Tracker::new(gpu, &tcfg, 5)?;
        liven(&tracker.store, &mut rng)?;
        let k = cfg.encoder.tokens;
        let tokens = Tensor::from_slice(gpu, &[k, tcfg.token_dim], &rng.normal_vec(k * tcfg.token_dim))?;
        let points: Vec<f32> = (0..k)
            .flat_map(|i| [rng.uniform() as f32 * 2.0 - 1.0, 0.0, 0.5, (i % 24) as f32 / 100.0])
            .collect();
        let token_points = Tensor::from_slice(gpu, &[k, 4], &points)?;
        let n = tcfg.queries_per_sample;
        let queries: Vec<f32> = (0..3 * n).map(|_| rng.uniform() as f32 * 1.6 - 0.8).collect();
        let queries = Tensor::from_slice(gpu, &[n, 3], &queries)?;
        let track = |rec: &mut velox_engine::Recorder, p: Precision| {
            rec.set_precision(p);
            tracker.record_tracks(rec, &tokens, &token_points, &queries)
        };
        for (p, t, e, m, over) in both_precisions(gpu, repeats, track)? {
            let shape = format!("{n} queries x 24 frames, {k} tokens");
            push(record("tracking network", shape, p, t, n as f64 / 1e6, "Mquery/s").error(e, m, over));
        }
        println!(
            "tracking network ({} config, {:.1} M parameters): {n} queries against {k} tokens",
            tcfg.name,
            tracker.store.num_parameters() as f64 / 1e6
        );
    }

    // DINOv2 over a video's 24 frames, and the generator's 20 Euler steps with guidance (two
    // network evaluations a step), both by the wall clock (one submission per block or step).
    {
        let paper = cfg.name == "paper";
        let gcfg = if paper { GeneratorConfig::paper() } else { GeneratorConfig::small() };
        let dcfg = if paper {
            Dinov2Config::large()
        } else {
            Dinov2Config { width: 128, depth: 2, heads: 2, hidden: 512, grid: 4, eps: 1e-6 }
        };
        let dino = Dinov2::random(gpu, &dcfg, 3)?;
        let (frames, size) = (gcfg.task.frames(), gcfg.image_size);
        let pixels = rng.normal_vec(frames * 3 * size * size);
        let features = |p: Precision| dino.patch_features(gpu, &pixels, frames, size, size, p)?.read::<f32>();
        let grid = size / PATCH;
        for (p, t, e, m, over) in wall_clock_both(repeats, features)? {
            let shape = format!("{frames} frames of {size} px, {} x {grid} patches", grid);
            let images = frames as f64;
            push(record("DINOv2 video", shape, p, t, images, "frame/s").error(e, m, over));
        }
        println!(
            "DINOv2 ({} wide, {} blocks, {:.1} M parameters, random weights) over {frames} frames of {size} px",
            dcfg.width,
            dcfg.depth,
            dcfg.num_parameters() as f64 / 1e6
        );
        let mut gcfg = GeneratorConfig { dino_width: dcfg.width, ..gcfg };
        gcfg.tokens = cfg.encoder.tokens;
        let generator = Generator::new(gpu, &gcfg, 7)?;
        liven(&generator.store, &mut rng)?;
        let rows = gcfg.cond_tokens();
        let condition = Condition {
            patches: Tensor::from_slice(gpu, &[rows, PATCH_VALUES], &rng.normal_vec(rows * PATCH_VALUES))?,
            dino: Some(Tensor::from_slice(gpu, &[rows, dcfg.width], &rng.normal_vec(rows * dcfg.width))?),
        };
        let steps = 20;
        let generate = |p: Precision| {
            let spec = GenerateSpec { steps, sampler: Sampler::Euler, guidance: 3.0, seed: 5, precision: p };
            generator.generate(&condition, &spec)?.read::<f32>()
        };
        for (p, t, e, m, over) in wall_clock_both(repeats, generate)? {
            let shape =
                format!("{} tokens, {rows} condition tokens, {steps} Euler steps, guidance", gcfg.tokens);
            push(record("generator 20 euler", shape, p, t, steps as f64, "step/s").error(e, m, over));
        }
        println!(
            "generator ({} config, {:.1} M parameters): {steps} Euler steps with guidance over {} tokens, \
             {rows} condition tokens",
            gcfg.name,
            generator.store.num_parameters() as f64 / 1e6,
            gcfg.tokens
        );
    }

    println!("paper, H100 (docs/models.md; targets on an H100: encoder < 100 ms, Gaussian decoder < 15 ms,");
    println!("surface decoder 16384 points with 100 Heun steps < 2 s):");
    for (what, ms) in PAPER_H100_MS {
        println!("  {what:<40} {ms:>10.2} ms");
    }
    if cfg.name != "paper" {
        println!("(these rows use the {} config, not the paper's: not comparable with the paper)", cfg.name);
    }
    Ok(out)
}
