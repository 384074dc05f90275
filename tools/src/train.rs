//! `velox train autoencoder`: trains the Velox autoencoder on a dataset made by `velox data`,
//! with a progress bar, a JSON-lines log, a loss plot and atomic, resumable checkpoints.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use velox_data::training::train_scene;
use velox_data::{Loader, LoaderOptions};
use velox_engine::Gpu;
use velox_models::checkpoint;
use velox_models::config::AutoencoderConfig;
use velox_models::files::write_bytes;
use velox_models::schedule::cooldown;
use velox_models::velox::autoencoder::{Autoencoder, StepLosses, TrainScene};

use crate::interrupt::{signal_name, Interrupt, Interrupted};
use crate::plot::loss_plot;
use crate::CliResult;

#[derive(Subcommand)]
pub enum TrainCommand {
    /// The autoencoder: encoder, 4D surface decoder and Gaussian decoder, on L_V + L_GS + 1e-4 L_C.
    ///
    /// Ctrl-C (SIGINT) or SIGTERM finishes the step under way, writes the checkpoint and exits
    /// with 130 (SIGINT) or 143 (SIGTERM), naming the checkpoint; --resume continues from it. A
    /// second signal quits at once, leaving the previous checkpoint whole.
    Autoencoder(AutoencoderArgs),
}

#[derive(Args, Clone)]
pub struct AutoencoderArgs {
    /// Dataset folder (scenes written by `velox data synth` or `velox data gltf`).
    #[arg(long)]
    pub data: PathBuf,
    /// Model sizes: paper, small, tiny, or a JSON config file.
    #[arg(long, default_value = "small")]
    pub config: String,
    /// Output folder: checkpoint.safetensors, log.jsonl, loss.png.
    #[arg(long)]
    pub out: PathBuf,
    /// Total optimiser steps (a resumed run continues up to this count).
    #[arg(long, default_value_t = 2000, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps: u64,
    /// Seed of the parameters and of every random draw of the run.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Continue from the output folder's checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Steps on each scene before the next one is loaded.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps_per_scene: u64,
    /// Steps between checkpoints (one is always written at the end).
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u64).range(1..))]
    pub checkpoint_every: u64,
    /// Steps between redraws of the loss plot.
    #[arg(long, default_value_t = 25, value_parser = clap::value_parser!(u64).range(1..))]
    pub plot_every: u64,
    /// Bring the learning rate down linearly over the last N steps of the run (to 1/(N+1) of
    /// the schedule's at the last step); 0 keeps the config's schedule to the end. A resumed
    /// run with the same --steps and --cooldown follows the same curve.
    #[arg(long, default_value_t = 0)]
    pub cooldown: u64,
}

/// What a finished run reports.
pub struct TrainSummary {
    pub model: Autoencoder,
    pub checkpoint: PathBuf,
    pub last: StepLosses,
    pub first: StepLosses,
    pub seconds: f64,
}

pub fn run(cmd: TrainCommand) -> CliResult<()> {
    match cmd {
        TrainCommand::Autoencoder(args) => {
            let interrupt = Interrupt::catch()?;
            let gpu = Gpu::new()?;
            let s = train_autoencoder(&gpu, &args, &interrupt)?;
            println!(
                "trained {} steps in {:.0} s: loss {:.4} -> {:.4}; checkpoint {}, log and loss plot in {}",
                s.model.store.step(),
                s.seconds,
                s.first.total,
                s.last.total,
                s.checkpoint.display(),
                args.out.display()
            );
            Ok(())
        }
    }
}

/// One line of `log.jsonl`.
#[derive(serde::Serialize, serde::Deserialize)]
struct LogLine {
    step: u64,
    seconds: f64,
    scene: String,
    total: f64,
    surface: f64,
    gaussians: f64,
    tokens: f64,
    grad_norm: f64,
    lr: f64,
    frame: usize,
    view: usize,
}

/// Keeps the log lines up to `step` (a resumed run rewrites what came after its checkpoint).
fn read_log(path: &Path, step: u64) -> Vec<LogLine> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<LogLine>(l).ok())
        .filter(|l| l.step <= step)
        .collect()
}

fn write_plot(path: &Path, log: &[LogLine]) -> CliResult<()> {
    let series = |f: fn(&LogLine) -> f64| log.iter().map(|l| (l.step as f64, f(l))).collect::<Vec<_>>();
    loss_plot(
        path,
        &[
            ("total", series(|l| l.total)),
            ("surface", series(|l| l.surface)),
            ("image", series(|l| l.gaussians)),
            ("tokens", series(|l| l.tokens)),
        ],
    )
}

/// What a run stopped by a NaN says of its checkpoint: written at some earlier step, it is
/// called good only once every value in it is checked finite.
fn last_good(checkpoint: &Path) -> String {
    if !checkpoint.exists() {
        return "no checkpoint was written yet".into();
    }
    match checkpoint::verify_finite(checkpoint) {
        Ok(info) => format!(
            "the last good checkpoint is {} (step {}, every value checked finite)",
            checkpoint.display(),
            info.step
        ),
        Err(e) => format!("the checkpoint is no good either: {e}"),
    }
}

/// Trains as the command does (also used by the demo). When `interrupt` asks for a stop, the
/// step under way is finished, the checkpoint written, and [`Interrupted`] returned.
pub fn train_autoencoder(
    gpu: &Gpu,
    args: &AutoencoderArgs,
    interrupt: &Interrupt,
) -> CliResult<TrainSummary> {
    std::fs::create_dir_all(&args.out).map_err(|e| format!("creating {}: {e}", args.out.display()))?;
    let checkpoint = args.out.join("checkpoint.safetensors");
    let log_path = args.out.join("log.jsonl");
    let mut model = if args.resume {
        if !checkpoint.exists() {
            return Err(format!(
                "--resume: {} holds no checkpoint.safetensors to resume from",
                args.out.display()
            )
            .into());
        }
        let m = Autoencoder::load(gpu, &checkpoint)?;
        if m.cfg.name != args.config {
            eprintln!(
                "note: resuming the checkpoint's config {:?} (--config {:?} is ignored)",
                m.cfg.name, args.config
            );
        }
        m
    } else {
        if checkpoint.exists() {
            return Err(format!(
                "{} already holds a checkpoint: pass --resume to continue it, or choose another --out",
                args.out.display()
            )
            .into());
        }
        Autoencoder::new(gpu, &AutoencoderConfig::named(&args.config)?, args.seed)?
    };
    let start_step = model.store.step();
    if start_step >= args.steps {
        return Err(format!(
            "the checkpoint is at step {start_step}, --steps {} asks for no more",
            args.steps
        )
        .into());
    }
    // The kept lines replace the log atomically; then each step is appended.
    let mut log = read_log(&log_path, start_step);
    let mut kept = String::new();
    for l in &log {
        kept += &(serde_json::to_string(l)? + "\n");
    }
    write_bytes(&log_path, kept.as_bytes())?;
    let log_error = |e: std::io::Error| format!("cannot write {}: {e}", log_path.display());
    let mut log_file = std::fs::OpenOptions::new().append(true).open(&log_path).map_err(log_error)?;

    let mut loader = Loader::spawn(
        &args.data,
        LoaderOptions { epochs: 0, shuffle: Some(args.seed), start: 0, prefetch: 2, images: true },
    )
    .map_err(|e| format!("dataset {}: {e}", args.data.display()))?;
    if loader.len == 0 {
        return Err(
            format!("{} holds no scenes; make some with `velox data synth`", args.data.display()).into()
        );
    }
    let bar = ProgressBar::new(args.steps);
    bar.set_position(start_step);
    bar.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} steps  {elapsed} (eta {eta})  {msg}")
            .expect("a valid template"),
    );
    let started = Instant::now();
    let elapsed_before = log.last().map(|l| l.seconds).unwrap_or(0.0);
    let mut scene: Option<(String, TrainScene)> = None;
    let mut first = None;
    let mut last = StepLosses::default();
    let mut step = start_step;
    while step < args.steps {
        // A new scene every `steps_per_scene` steps (a one-scene dataset is read once).
        if scene.is_none() || (loader.len > 1 && step.is_multiple_of(args.steps_per_scene)) {
            let s = loader.next().ok_or("the data loader stopped")?.map_err(|e| format!("dataset: {e}"))?;
            let name = s.dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            scene = Some((name, train_scene(gpu, &s)?));
        }
        let (name, data) = scene.as_ref().expect("loaded above");
        step += 1;
        model.lr_scale = cooldown(args.steps, args.cooldown, step);
        let losses = match model.train_step(data, step, &mut Autoencoder::step_rng(args.seed, step)) {
            Ok(l) => l,
            Err(e) => {
                bar.abandon();
                let kept = last_good(&checkpoint);
                return Err(format!("training stopped at step {step}: {e}; {kept}").into());
            }
        };
        first.get_or_insert(losses);
        last = losses;
        let seconds = elapsed_before + started.elapsed().as_secs_f64();
        let line = LogLine {
            step,
            seconds,
            scene: name.clone(),
            total: losses.total,
            surface: losses.surface,
            gaussians: losses.gaussians,
            tokens: losses.tokens,
            grad_norm: losses.grad_norm,
            lr: losses.lr,
            frame: losses.frame,
            view: losses.view,
        };
        writeln!(log_file, "{}", serde_json::to_string(&line)?).map_err(log_error)?;
        log.push(line);
        let rate = (step - start_step) as f64 / started.elapsed().as_secs_f64().max(1e-9);
        bar.set_message(format!(
            "loss {:.4} (surface {:.4}, image {:.5})  {rate:.2} steps/s",
            losses.total, losses.surface, losses.gaussians
        ));
        bar.set_position(step);
        if step.is_multiple_of(args.plot_every) {
            write_plot(&args.out.join("loss.png"), &log)?;
        }
        if step.is_multiple_of(args.checkpoint_every) {
            model.save(&checkpoint)?;
        }
        if let Some(signal) = interrupt.requested().filter(|_| step < args.steps) {
            if !step.is_multiple_of(args.checkpoint_every) {
                model.save(&checkpoint)?;
            }
            write_plot(&args.out.join("loss.png"), &log)?;
            bar.abandon();
            let message = format!(
                "{}: stopped after step {step} of {}; checkpoint {} holds step {step} (continue with --resume)",
                signal_name(signal),
                args.steps,
                checkpoint.display()
            );
            return Err(Interrupted { signal, message }.into());
        }
    }
    model.save(&checkpoint)?;
    write_plot(&args.out.join("loss.png"), &log)?;
    bar.finish();
    let first = first.expect("at least one step ran");
    Ok(TrainSummary { model, checkpoint, first, last, seconds: started.elapsed().as_secs_f64() })
}
