//! `velox bench models`: the Velox autoencoder's parts at the paper config with random weights
//! (the small config on CPU devices such as lavapipe, or with `--quick`), timed against the
//! paper's H100 figures (MODELS.md).
//!
//! - encoder: a random 4D cloud (points on a sphere whose radius changes over the 24 frames,
//!   random colours; 1.44 M points at the paper config) to k x 32 tokens, one recording timed
//!   by GPU timestamps;
//! - Gaussian decoder, one frame: its queries are the occupied voxels of a sphere of radius 0.8
//!   at the config's grid, a realistic surface count: about 11.3k of 64^3 at the paper config
//!   (x 64 = 725k Gaussians), about 2.9k of 32^3 at the small one; the record's shape gives
//!   it. One recording timed by GPU timestamps;
//! - 4D surface decoder: sampling 16384 points with Heun, 20 and 100 steps (1024 points on a
//!   CPU device; 256 points and 4 and 20 steps with `--quick`), timed as the whole sampling
//!   call (one submission per step and chunk, so wall clock, `gpu_timed: false`).
//!
//! Weights: the store's initialisation, with every parameter that starts at zero (adaLN-Zero
//! maps, output layers, biases) drawn from N(0, 0.02^2) instead, so that no path is a
//! constant. Error: there is no f16 model path yet, so no f16-against-f32 error exists; each
//! record reports instead the NMSE of its last timed run against a first run on the same
//! input (a determinism check: atomics may reorder sums), and says so in `error_over`.

use velox_engine::rng::Rng;
use velox_engine::stats::{max_abs_err, nmse};
use velox_engine::{Gpu, Result, Tensor};
use velox_models::config::AutoencoderConfig;
use velox_models::params::ParamStore;
use velox_models::velox::autoencoder::{tau_of, FRAMES};
use velox_models::velox::cloud;
use velox_models::velox::encoder::Encoder;
use velox_models::velox::gaussians::{occupied_voxels, GaussianDecoder};
use velox_models::velox::surface::{SampleSpec, Sampler, SurfaceDecoder};

use super::{print_header, print_row, time_gpu, Record};

/// The paper's H100 times in ms (MODELS.md): encoder, Gaussian decoder one frame, 4D surface
/// decoder 16384 points (the table does not give its steps).
const PAPER_H100_MS: [(&str, f64); 3] = [
    ("encoder, 1.44 M points -> 8192 tokens", 387.66),
    ("Gaussian decoder, one frame", 32.71),
    ("4D surface decoder, 16384 points", 24_800.0),
];

const ERROR_OVER: &str =
    "no f16 model path yet: NMSE of the last timed run against a first run (determinism check)";

struct Sizes {
    cfg: AutoencoderConfig,
    points: usize,
    surface_points: usize,
    steps: [usize; 2],
}

fn sizes(gpu: &Gpu, quick: bool) -> Sizes {
    if quick {
        // Seconds on lavapipe: fewer points and steps for the surface decoder.
        Sizes { cfg: AutoencoderConfig::small(), points: 24_000, surface_points: 256, steps: [4, 20] }
    } else if gpu.caps().kind == "CPU" {
        Sizes { cfg: AutoencoderConfig::small(), points: 24_000, surface_points: 1024, steps: [20, 100] }
    } else {
        Sizes { cfg: AutoencoderConfig::paper(), points: 1_440_000, surface_points: 16384, steps: [20, 100] }
    }
}

/// Draws every parameter that starts at exactly zero from N(0, 0.02^2).
fn liven(store: &ParamStore, rng: &mut Rng) -> Result<()> {
    let mut p: Vec<f32> = store.flat_params().read()?;
    for v in p.iter_mut().filter(|v| **v == 0.0) {
        *v = (0.02 * rng.normal()) as f32;
    }
    store.flat_params().write(&p)
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

fn errors(first: &[f32], last: &[f32]) -> (f64, f64) {
    let reference: Vec<f64> = first.iter().map(|&v| v as f64).collect();
    (nmse(last, &reference), max_abs_err(last, &reference))
}

pub fn run(gpu: &Gpu, quick: bool, repeats: u32) -> Result<Vec<Record>> {
    let s = sizes(gpu, quick);
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
    let record = |name: &str, shape: String, t: (f64, f64, bool), work: f64, unit: &str| {
        Record::timed(name, shape, "f32", &device, t, repeats, work / (t.0 * 1e-3), unit)
            .error(0.0, 0.0, ERROR_OVER)
    };

    // Encoder.
    {
        let mut b = ParamStore::builder();
        Encoder::register(&mut b, "encoder", &cfg.encoder)?;
        let store = b.build(gpu, 1)?;
        liven(&store, &mut rng)?;
        let encoder = Encoder::new(gpu, &store, "encoder", &cfg.encoder)?;
        let cloud = cloud::upload(gpu, &sphere_cloud(s.points, &mut rng))?;
        let encode =
            |rec: &mut velox_engine::Recorder| encoder.forward(rec, &cloud, &mut Rng::new(5)).map(|o| o.0);
        let mut rec = gpu.recorder()?;
        let first_t = encode(&mut rec)?;
        rec.submit()?;
        let first: Vec<f32> = first_t.read()?;
        let mut last = None;
        let t = time_gpu(gpu, repeats, |rec| {
            last = Some(encode(rec)?);
            Ok(())
        })?;
        let last: Vec<f32> = last.expect("time_gpu runs at least once").read()?;
        let (e, m) = errors(&first, &last);
        let (k, d) = (cfg.encoder.tokens, cfg.encoder.token_dim);
        push(Record {
            nmse: e,
            max_abs_err: m,
            ..record(
                "encoder",
                format!("{} points -> {k}x{d}", s.points),
                t,
                s.points as f64 / 1e6,
                "Mpoint/s",
            )
        });
    }

    // Gaussian decoder, one frame.
    {
        let g = &cfg.gaussians;
        let mut b = ParamStore::builder();
        GaussianDecoder::register(&mut b, "gaussians", g, cfg.encoder.token_dim)?;
        let store = b.build(gpu, 2)?;
        liven(&store, &mut rng)?;
        let decoder = GaussianDecoder::new(gpu, &store, "gaussians", g)?;
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
        let decode =
            |rec: &mut velox_engine::Recorder| decoder.forward(rec, &tokens, &c, 0.0).map(|o| o.0.means);
        let mut rec = gpu.recorder()?;
        let first_t = decode(&mut rec)?;
        rec.submit()?;
        let first: Vec<f32> = first_t.read()?;
        let mut last = None;
        let t = time_gpu(gpu, repeats, |rec| {
            last = Some(decode(rec)?);
            Ok(())
        })?;
        let last: Vec<f32> = last.expect("time_gpu runs at least once").read()?;
        let (e, m) = errors(&first, &last);
        let n = v * g.gaussians_per_voxel;
        push(Record {
            nmse: e,
            max_abs_err: m,
            ..record(
                "gaussian decoder frame",
                format!("{v} vox of {0}^3 -> {n} Gaussians", g.grid),
                t,
                n as f64 / 1e6,
                "MGauss/s",
            )
        });
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
            let spec = SampleSpec { points: s.surface_points, steps, sampler: Sampler::Heun, seed: 9 };
            let sample = || -> Result<(Vec<f32>, f64)> {
                let t0 = std::time::Instant::now();
                let x = decoder.sample(&tokens, 0.1, &spec)?;
                let v: Vec<f32> = x.read()?;
                Ok((v, t0.elapsed().as_secs_f64() * 1e3))
            };
            let (first, _) = sample()?;
            let mut times = Vec::new();
            let mut last = Vec::new();
            for _ in 0..repeats {
                let (v, ms) = sample()?;
                times.push(ms);
                last = v;
            }
            times.sort_by(f64::total_cmp);
            let (e, m) = errors(&first, &last);
            let flops = 2.0
                * steps as f64
                * SurfaceDecoder::forward_flops(&cfg.surface, cfg.encoder.token_dim, s.surface_points, k)
                    as f64;
            push(Record {
                nmse: e,
                max_abs_err: m,
                ..record(
                    &format!("surface decoder heun {steps}"),
                    format!("{} points, {} evaluations", s.surface_points, 2 * steps),
                    (times[times.len() / 2], times[0], false),
                    flops / 1e12,
                    "TFLOP/s",
                )
            });
        }
    }

    println!(
        "paper, H100 (MODELS.md; the issue's bars on an H100: encoder < 100 ms, Gaussian decoder < 15 ms,"
    );
    println!("surface decoder 16384 points with 100 Heun steps < 2 s):");
    for (what, ms) in PAPER_H100_MS {
        println!("  {what:<40} {ms:>10.2} ms");
    }
    if cfg.name != "paper" {
        println!("(these rows use the {} config, not the paper's: not comparable with the paper)", cfg.name);
    }
    Ok(out)
}
