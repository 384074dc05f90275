//! `velox bench train`: training throughput, samples per second against the micro-batch size,
//! for a config on the present device, in f32 and in f16 (mixed precision), with the time of a
//! step split as the trainer splits it (`velox_models::train::trainer::TimeSplit`: data,
//! compute, all-reduce, optimiser; forward and backward within compute where the model measures
//! them), the dispatches a step records, the peak device memory of a step, and the GPU time of
//! a step by kernel family (`velox_engine::profile::family`: matmul, attention, norm,
//! elementwise, reduce, layout, raster, cast, optimiser).
//!
//! The samples: one procedural scene rendered into a temporary folder and read back (32 px and
//! 4000 points on a CPU device or with `--quick`, 128 px and 60000 points on a GPU), the same
//! scene in every slot, held in memory, so the data part of the split is nothing here. Per
//! precision and batch size (1, 2, 4 on a CPU device or with `--quick`; up to 16 on a GPU; or
//! `--batches`): a fresh model with the config's `batch` set to it, one untimed warm-up step,
//! then `--repeats` steps of the library trainer, each timed as a whole on the wall clock
//! (`gpu_timed: false`); samples/s is the batch over the median step, and the split shown is
//! that step's. The peak memory is the most the engine's buffers held during the timed steps
//! (the model, its moments and f16 copies included). One more step runs with per-dispatch
//! timestamps (which slow it, so it is not among the timed ones) for the dispatch count and
//! the family split, and for its submissions (each a host wait). `--model voxels|tracker|generator` times a model downstream of the
//! encoder the same way on one scene's tokens ([`run_token_model`]).

use std::collections::BTreeMap;
use velox_data::format::write_scene;
use velox_data::{procedural, read_scene, SynthOptions};
use velox_tasks::training::train_scene;

use velox_engine::{profile, Error, Gpu, Precision, Result};
use velox_io::cloud::CHANNELS;
use velox_models::config::AutoencoderConfig;
use velox_models::run::{RunRequest, RunSettings};
use velox_models::train::collective::SingleProcess;
use velox_models::train::trainer::Trainer;
use velox_models::velox::autoencoder::{Autoencoder, TrainScene};
use velox_models::Model;

use super::Record;

/// Renders the benchmark's scene and loads it for training.
fn scene(gpu: &Gpu, small: bool) -> Result<TrainScene> {
    let dir = std::env::temp_dir().join(format!("velox-bench-train-{}", std::process::id()));
    let (res, points) = if small { (32, 4000) } else { (128, 60_000) };
    let (_, mesh) = procedural::scene(3, None)?;
    let opts = SynthOptions { res, points, supersample: 1, tracks: 8, ..Default::default() };
    let made = write_scene(gpu, &mesh, "bench train", None, 3, &opts, &dir, &mut |_| {})
        .and_then(|_| read_scene(&dir, true))
        .and_then(|s| train_scene(gpu, &s));
    let _ = std::fs::remove_dir_all(&dir);
    Ok(made?)
}

/// What one profiled step recorded: its dispatches, its submissions (each one a host wait: a
/// recorder's submit waits for its work) and its GPU milliseconds by kernel family.
pub struct StepProfile {
    pub dispatches: u64,
    pub submits: u64,
    pub family_ms: BTreeMap<String, f64>,
}

/// Runs `step` with per-dispatch timestamps and gathers what it recorded.
pub fn profile_step(step: impl FnOnce() -> Result<()>) -> Result<StepProfile> {
    let was = profile::enabled();
    profile::set_enabled(true);
    profile::take();
    let submits = profile::submits();
    let result = step();
    let submits = profile::submits() - submits;
    let totals = profile::take();
    profile::set_enabled(was);
    result?;
    let mut family_ms = BTreeMap::new();
    for t in &totals {
        *family_ms.entry(profile::family(&t.kernel).to_string()).or_insert(0.0) += t.ns / 1e6;
    }
    Ok(StepProfile { dispatches: totals.iter().map(|t| t.dispatches).sum(), submits, family_ms })
}

/// `family ms, ...`, the longest first.
fn longest_first(family_ms: &BTreeMap<String, f64>) -> String {
    let mut families: Vec<(&String, &f64)> = family_ms.iter().collect();
    families.sort_by(|a, b| b.1.total_cmp(a.1));
    families.iter().map(|(f, ms)| format!("{f} {ms:.1}")).collect::<Vec<_>>().join(", ")
}

pub fn run(
    gpu: &Gpu,
    quick: bool,
    repeats: u32,
    config: &str,
    batches: Option<&[usize]>,
    precisions: &[Precision],
    overlap: Option<bool>,
) -> Result<Vec<Record>> {
    let small = quick;
    let batches = batches.map_or(if small { vec![1, 2, 4] } else { vec![1, 2, 4, 8, 16] }, <[usize]>::to_vec);
    let base = AutoencoderConfig::named(config)?;
    let device = gpu.caps().name.clone();
    let data = scene(gpu, small)?;
    println!(
        "device: {device} ({}); the {} autoencoder config on one {}-point scene; {repeats} timed steps \
         after a warm-up, median shown",
        gpu.caps().kind,
        base.name,
        data.cloud_host.len() / CHANNELS
    );
    println!(
        "{:>5} {:>6} {:>10} {:>10} {:>11} {:>12} {:>14} {:>8} {:>13} {:>11} {:>14} {:>10}",
        "prec",
        "batch",
        "samples/s",
        "step ms",
        "(apart ms)",
        "compute ms",
        "(fwd / bwd)",
        "(host)",
        "optimiser ms",
        "dispatches",
        "submits/waits",
        "peak MiB"
    );
    let mut out = Vec::new();
    for &precision in precisions {
        for &batch in &batches {
            let cfg = AutoencoderConfig { batch, ..base.clone() };
            cfg.validate()?;
            let mut model = Autoencoder::new(gpu, &cfg, 0)?;
            let steps = 1 + repeats as u64;
            let request =
                RunRequest { steps: Some(2 * steps + 1), precision: Some(precision), ..Default::default() };
            let settings = RunSettings::new(&request, vec!["bench".into()], batch as u64, 1)?;
            let mut trainer = Trainer::new(&mut model, &SingleProcess, settings)?;
            if let Some(on) = overlap {
                trainer.set_overlap(on);
            }
            trainer.repeat_steps(&[&data], 1..2)?;
            gpu.reset_peak_memory();
            let reports = trainer.repeat_steps(&[&data], 2..steps + 1)?;
            let peak = gpu.memory().1;
            let profiled = profile_step(|| trainer.repeat_steps(&[&data], steps + 1..steps + 2).map(|_| ()))?;
            // Where steps overlap (Trainer::set_overlap), as many more without it.
            let unoverlapped = if trainer.overlaps() {
                trainer.set_overlap(false);
                let more = trainer.repeat_steps(&[&data], steps + 2..2 * steps + 1)?;
                let mut ms: Vec<f64> = more.iter().map(|r| r.time.total() * 1e3).collect();
                ms.sort_by(f64::total_cmp);
                Some(ms[ms.len() / 2])
            } else {
                None
            };
            let mut timed: Vec<_> = reports.iter().collect();
            timed.sort_by(|a, b| a.time.total().total_cmp(&b.time.total()));
            // The median step, with its own split (so the parts add up to its time).
            let split = timed[timed.len() / 2].time.scale(1e3);
            let (median, min) = (split.total(), timed[0].time.total() * 1e3);
            if !median.is_finite() || median <= 0.0 {
                return Err(Error::Invalid(format!("batch {batch}: a step took {median} ms")));
            }
            let rate = batch as f64 / (median * 1e-3);
            let passes = match (split.forward, split.backward) {
                (Some(f), Some(b)) => format!("{f:.1} / {b:.1}"),
                _ => "-".into(),
            };
            let host = split.host.map_or("-".into(), |h| format!("{h:.1}"));
            let apart = unoverlapped.map_or("-".into(), |ms| format!("{ms:.1}"));
            let name = precision.name();
            println!(
                "{name:>5} {batch:>6} {rate:>10.3} {median:>10.1} {apart:>11} {:>12.1} {passes:>14} {host:>8} {:>13.2} {:>11} {:>14} {:>10.1}",
                split.compute,
                split.optimiser,
                profiled.dispatches,
                profiled.submits,
                peak as f64 / (1 << 20) as f64
            );
            println!("{:>12} GPU ms by family (profiled step): {}", "", longest_first(&profiled.family_ms));
            let shape = format!("{} config, batch {batch}", cfg.name);
            let record = Record::timed(
                "train step",
                shape,
                name,
                &device,
                (median, min, false),
                repeats,
                rate,
                "samples/s",
            );
            let record = Record {
                time_split_ms: Some(split),
                dispatches_per_step: Some(profiled.dispatches),
                submits_per_step: Some(profiled.submits),
                peak_memory_bytes: Some(peak),
                step_ms_unoverlapped: unoverlapped,
                family_ms: Some(profiled.family_ms),
                ..record
            };
            super::keep(&record);
            out.push(record);
        }
    }
    println!(
        "compute is the model's forward (to the end of its renders) and backward passes, fwd / bwd \
         their GPU time and host the time the device waited on the host before each submission \
         (recording, drawing, uploads; where a step is recorded while the last runs, only from \
         the last one's end: apart ms is the median step recorded after the last one's wait \
         instead, on a device where steps overlap); on one process the backward pass \
         records the optimiser's update too (optimiser ms is what is left outside the passes; its \
         GPU time is the family split's 'optimiser'), and all-reduce is nothing; the family split \
         comes from one more step with a timestamp per dispatch"
    );
    Ok(out)
}

/// The models downstream of the encoder that `velox bench train --model` times.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ModelArg {
    Autoencoder,
    Voxels,
    Tracker,
    Generator,
}

/// `bench train --model voxels|tracker|generator`: the benchmark's scene written to a folder,
/// encoded by an untrained small autoencoder (its tokens have the shapes a trained one gives;
/// the tracker's from the scene's RGBD video), then a run of `1 + repeats` steps of the model
/// through the command's own training function in each precision. The figures are means over
/// the run's steps (the first, warm-up one included): step time, dispatches (the process's
/// count over the run), the peak device memory, and the GPU time by kernel family (every step
/// profiled, so the step times include the timestamps' cost).
pub fn run_token_model(
    gpu: &Gpu,
    model: ModelArg,
    quick: bool,
    repeats: u32,
    config: &str,
    precisions: &[Precision],
) -> crate::CliResult<Vec<Record>> {
    use crate::interrupt::Interrupt;
    use crate::train::{
        train_generator, train_tracker, train_voxels, GeneratorArgs, RunArgs, TaskArg, TokenModelArgs,
    };
    use velox_models::velox::tokens::CloudSource;
    use velox_tasks::encode::{encode_dataset, EncodeOptions};

    let small = quick;
    let dir = std::env::temp_dir().join(format!("velox-bench-train-tokens-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let data = dir.join("data");
    let (res, points) = if small { (32, 4000) } else { (128, 60_000) };
    let (_, mesh) = procedural::scene(3, None)?;
    let opts = SynthOptions { res, points, supersample: 1, tracks: 64, ..Default::default() };
    write_scene(gpu, &mesh, "bench train", None, 3, &opts, &data.join("scene_00000"), &mut |_| {})?;
    let ae = dir.join("autoencoder.safetensors");
    Autoencoder::new(gpu, &AutoencoderConfig::small(), 0)?.save(&ae)?;
    let source = if model == ModelArg::Tracker { CloudSource::Video } else { CloudSource::Points };
    let encode = EncodeOptions {
        checkpoint: ae,
        data: data.clone(),
        out: None,
        seed: 0,
        precision: Precision::F32,
        force: false,
        source,
        video_points: velox_data::rgbd::DEFAULT_POINTS,
    };
    encode_dataset(gpu, &encode, &mut ())?;
    let device = gpu.caps().name.clone();
    let name = format!("{model:?}").to_lowercase();
    println!(
        "device: {device} ({}); the {config} {name} config on one scene's tokens (an untrained small \
         autoencoder's); {} steps, means over them",
        gpu.caps().kind,
        1 + repeats
    );
    println!(
        "{:>5} {:>10} {:>10} {:>12} {:>11} {:>14} {:>10}",
        "prec", "samples/s", "step ms", "compute ms", "dispatches", "submits/waits", "peak MiB"
    );
    let mut out = Vec::new();
    for &precision in precisions {
        let steps = 1 + repeats as u64;
        let run = RunArgs {
            out: dir.join(format!("run-{}", precision.name())),
            steps: Some(steps),
            seed: None,
            resume: false,
            init: None,
            steps_per_scene: None,
            accumulate: None,
            checkpoint_every: steps,
            plot_every: steps,
            cooldown: None,
            stop_at: None,
            precision: Some(match precision {
                Precision::F32 => crate::decode::PrecisionArg::F32,
                Precision::F16 => crate::decode::PrecisionArg::F16,
            }),
            overlap: None,
        };
        let args = TokenModelArgs {
            data: data.clone(),
            tokens: None,
            checkpoint: None,
            config: Some(config.into()),
            run,
        };
        gpu.reset_peak_memory();
        let before = profile::dispatches();
        let mut outcome = None;
        let profiled = profile_step(|| {
            let never = Interrupt::never();
            let done = match model {
                ModelArg::Voxels => train_voxels(gpu, &args, &never, &SingleProcess),
                ModelArg::Tracker => train_tracker(gpu, &args, &never, &SingleProcess),
                ModelArg::Generator => {
                    let g = GeneratorArgs { model: args.clone(), task: TaskArg::Video, dinov2: None };
                    train_generator(gpu, &g, &never, &SingleProcess)
                }
                ModelArg::Autoencoder => unreachable!("the autoencoder has its own bench"),
            };
            outcome = Some(done.map_err(|e| Error::Invalid(e.to_string()))?);
            Ok(())
        })?;
        let dispatches = (profile::dispatches() - before) / steps;
        let submits = profiled.submits / steps;
        let peak = gpu.memory().1;
        let o = outcome.expect("the run finished");
        let split = o.time.scale(1e3);
        let step_ms = split.total();
        let rate = o.settings.global_batch as f64 / (step_ms * 1e-3);
        let label = precision.name();
        println!(
            "{label:>5} {rate:>10.3} {step_ms:>10.1} {:>12.1} {dispatches:>11} {submits:>14} {:>10.1}",
            split.compute,
            peak as f64 / (1 << 20) as f64
        );
        let family_ms: BTreeMap<String, f64> =
            profiled.family_ms.into_iter().map(|(f, ms)| (f, ms / steps as f64)).collect();
        println!("{:>12} GPU ms by family, a step: {}", "", longest_first(&family_ms));
        let shape = format!("{config} {name} config, batch {}", o.settings.global_batch);
        let record = Record::timed(
            "train step",
            shape,
            label,
            &device,
            (step_ms, step_ms, false),
            repeats,
            rate,
            "samples/s",
        );
        let record = Record {
            time_split_ms: Some(split),
            dispatches_per_step: Some(dispatches),
            submits_per_step: Some(submits),
            peak_memory_bytes: Some(peak),
            family_ms: Some(family_ms),
            ..record
        };
        super::keep(&record);
        out.push(record);
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(out)
}
