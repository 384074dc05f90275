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
//! the family split.

use std::collections::BTreeMap;
use velox_data::format::write_scene;
use velox_data::training::train_scene;
use velox_data::{procedural, read_scene, SynthOptions};

use velox_engine::{profile, Error, Gpu, Precision, Result};
use velox_models::config::AutoencoderConfig;
use velox_models::run::{RunRequest, RunSettings};
use velox_models::train::collective::SingleProcess;
use velox_models::train::trainer::Trainer;
use velox_models::velox::autoencoder::{Autoencoder, TrainScene};
use velox_models::velox::cloud::CHANNELS;

use super::Record;

/// Renders the benchmark's scene and loads it for training.
fn scene(gpu: &Gpu, small: bool) -> Result<TrainScene> {
    let dir = std::env::temp_dir().join(format!("velox-bench-train-{}", std::process::id()));
    let (res, points) = if small { (32, 4000) } else { (128, 60_000) };
    let (_, mesh) = procedural::scene(3, None)?;
    let opts = SynthOptions { res, points, supersample: 1, tracks: 8 };
    let made = write_scene(gpu, &mesh, "bench train", None, 3, &opts, &dir, &mut |_| {})
        .and_then(|_| read_scene(&dir, true))
        .and_then(|s| train_scene(gpu, &s));
    let _ = std::fs::remove_dir_all(&dir);
    Ok(made?)
}

/// What one profiled step recorded: its dispatches and its GPU milliseconds by kernel family.
pub struct StepProfile {
    pub dispatches: u64,
    pub family_ms: BTreeMap<String, f64>,
}

/// Runs `step` with per-dispatch timestamps and gathers what it recorded.
pub fn profile_step(step: impl FnOnce() -> Result<()>) -> Result<StepProfile> {
    let was = profile::enabled();
    profile::set_enabled(true);
    profile::take();
    let result = step();
    let totals = profile::take();
    profile::set_enabled(was);
    result?;
    let mut family_ms = BTreeMap::new();
    for t in &totals {
        *family_ms.entry(profile::family(&t.kernel).to_string()).or_insert(0.0) += t.ns / 1e6;
    }
    Ok(StepProfile { dispatches: totals.iter().map(|t| t.dispatches).sum(), family_ms })
}

pub fn run(
    gpu: &Gpu,
    quick: bool,
    repeats: u32,
    config: &str,
    batches: Option<&[usize]>,
    precisions: &[Precision],
) -> Result<Vec<Record>> {
    let cpu = gpu.caps().kind == "CPU";
    let small = quick || cpu;
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
        "{:>5} {:>6} {:>10} {:>10} {:>12} {:>14} {:>13} {:>11} {:>10}",
        "prec",
        "batch",
        "samples/s",
        "step ms",
        "compute ms",
        "(fwd / bwd)",
        "optimiser ms",
        "dispatches",
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
                RunRequest { steps: Some(steps + 1), precision: Some(precision), ..Default::default() };
            let settings = RunSettings::new(&request, vec!["bench".into()], batch as u64, 1)?;
            let mut trainer = Trainer::new(&mut model, &SingleProcess, settings)?;
            trainer.repeat_steps(&[&data], 1..2)?;
            gpu.reset_peak_memory();
            let reports = trainer.repeat_steps(&[&data], 2..steps + 1)?;
            let peak = gpu.memory().1;
            let profiled = profile_step(|| trainer.repeat_steps(&[&data], steps + 1..steps + 2).map(|_| ()))?;
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
            let name = precision.name();
            println!(
                "{name:>5} {batch:>6} {rate:>10.3} {median:>10.1} {:>12.1} {passes:>14} {:>13.2} {:>11} {:>10.1}",
                split.compute,
                split.optimiser,
                profiled.dispatches,
                peak as f64 / (1 << 20) as f64
            );
            let mut families: Vec<(&String, &f64)> = profiled.family_ms.iter().collect();
            families.sort_by(|a, b| b.1.total_cmp(a.1));
            let families: Vec<String> = families.iter().map(|(f, ms)| format!("{f} {ms:.1}")).collect();
            println!("{:>12} GPU ms by family (profiled step): {}", "", families.join(", "));
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
            out.push(Record {
                time_split_ms: Some(split),
                dispatches_per_step: Some(profiled.dispatches),
                peak_memory_bytes: Some(peak),
                family_ms: Some(profiled.family_ms),
                ..record
            });
        }
    }
    println!(
        "compute is the model's forward (to the end of its renders) and backward passes; all-reduce \
         is nothing on one process; the family split comes from one more step with a timestamp per \
         dispatch"
    );
    Ok(out)
}
