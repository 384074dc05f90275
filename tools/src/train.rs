//! `velox train autoencoder`: trains the Velox autoencoder on a dataset made by `velox data`,
//! with a progress bar, a JSON-lines log, a loss plot and atomic, resumable checkpoints.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use velox_data::format::list_scenes;
use velox_data::order::step_position;
use velox_data::training::train_scene;
use velox_data::{Loader, LoaderOptions};
use velox_engine::Gpu;
use velox_models::checkpoint;
use velox_models::config::AutoencoderConfig;
use velox_models::files::write_bytes;
use velox_models::run::{RunRequest, RunSettings};
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
    /// Total optimiser steps [default: 2000]. A resumed run continues to the total it started
    /// with, or to this one when it is given.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps: Option<u64>,
    /// Seed of the parameters, of the scene order and of every random draw of the run
    /// [default: 0].
    #[arg(long)]
    pub seed: Option<u64>,
    /// Continue the run in the output folder from its checkpoint, with the settings the run
    /// started with (seed, steps per scene, cooldown, total steps), so that it repeats the
    /// uninterrupted run exactly. A --seed, --steps-per-scene or --cooldown other than the
    /// run's, or a dataset whose scenes changed, is refused; --steps sets a new total.
    #[arg(long)]
    pub resume: bool,
    /// Steps on each scene before the next one is loaded [default: 8].
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps_per_scene: Option<u64>,
    /// Steps between checkpoints (one is always written at the end).
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u64).range(1..))]
    pub checkpoint_every: u64,
    /// Steps between redraws of the loss plot.
    #[arg(long, default_value_t = 25, value_parser = clap::value_parser!(u64).range(1..))]
    pub plot_every: u64,
    /// Bring the learning rate down linearly over the last N steps of the run (to 1/(N+1) of
    /// the schedule's at the last step); 0 keeps the config's schedule to the end [default: 0].
    #[arg(long)]
    pub cooldown: Option<u64>,
    /// Stop after this step as an interrupted run does (write the checkpoint and exit, with
    /// status 0): --resume continues the same run later, as if it had not stopped.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub stop_at: Option<u64>,
}

impl AutoencoderArgs {
    /// The run settings the command line gives (`None` where it leaves one out).
    fn request(&self) -> RunRequest {
        RunRequest {
            seed: self.seed,
            steps: self.steps,
            steps_per_scene: self.steps_per_scene,
            cooldown: self.cooldown,
        }
    }
}

/// What a finished run reports.
pub struct TrainSummary {
    pub model: Autoencoder,
    pub checkpoint: PathBuf,
    pub last: StepLosses,
    pub first: StepLosses,
    pub seconds: f64,
    /// The run's total steps.
    pub steps: u64,
    /// Whether it stopped before them, at --stop-at.
    pub stopped: bool,
}

pub fn run(cmd: TrainCommand) -> CliResult<()> {
    match cmd {
        TrainCommand::Autoencoder(args) => {
            let interrupt = Interrupt::catch()?;
            let gpu = Gpu::new()?;
            let s = train_autoencoder(&gpu, &args, &interrupt)?;
            if s.stopped {
                println!(
                    "stopped after step {} of {} as --stop-at asks: checkpoint {} holds it (continue with --resume)",
                    s.model.store.step(),
                    s.steps,
                    s.checkpoint.display()
                );
                return Ok(());
            }
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

/// The settings of a run resumed from `checkpoint`: the stored ones (see
/// [`RunSettings::resume`]), or, from a checkpoint written before runs stored them, the command
/// line's.
fn resumed_settings(checkpoint: &Path, request: &RunRequest, names: Vec<String>) -> CliResult<RunSettings> {
    let Some(stored) = Autoencoder::checkpoint_run(checkpoint)? else {
        eprintln!(
            "note: {} does not store its run's settings (it predates that): the command line's are \
             used, and the scene order may differ from the run's first part",
            checkpoint.display()
        );
        return Ok(RunSettings::new(request, names));
    };
    let settings = stored.resume(request, &names, checkpoint)?;
    if settings.steps != stored.steps && settings.cooldown > 0 {
        eprintln!(
            "note: the run now ends at step {} instead of {}, and its cooldown of {} steps moves with the end",
            settings.steps, stored.steps, settings.cooldown
        );
    }
    Ok(settings)
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
    let names: Vec<String> = list_scenes(&args.data)
        .map_err(|e| format!("dataset {}: {e}", args.data.display()))?
        .iter()
        .map(|d| d.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default())
        .collect();
    if names.is_empty() {
        return Err(
            format!("{} holds no scenes; make some with `velox data synth`", args.data.display()).into()
        );
    }
    let (mut model, settings) = if args.resume {
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
        (m, resumed_settings(&checkpoint, &args.request(), names)?)
    } else {
        if checkpoint.exists() {
            return Err(format!(
                "{} already holds a checkpoint: pass --resume to continue it, or choose another --out",
                args.out.display()
            )
            .into());
        }
        let settings = RunSettings::new(&args.request(), names);
        (Autoencoder::new(gpu, &AutoencoderConfig::named(&args.config)?, settings.seed)?, settings)
    };
    let start_step = model.store.step();
    if start_step >= settings.steps {
        return Err(format!(
            "the checkpoint is at step {start_step} of a run of {} steps: pass a larger --steps to go on",
            settings.steps
        )
        .into());
    }
    if let Some(at) = args.stop_at.filter(|&at| at <= start_step || at > settings.steps) {
        return Err(format!(
            "--stop-at {at} is not a step to come: the run goes from step {} to {}",
            start_step + 1,
            settings.steps
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

    // The loader starts at the scene of the next step (see velox_data::order).
    let start = step_position(start_step + 1, settings.steps_per_scene);
    let options = LoaderOptions { epochs: 0, shuffle: Some(settings.seed), start, prefetch: 2, images: true };
    let mut loader =
        Loader::spawn(&args.data, options).map_err(|e| format!("dataset {}: {e}", args.data.display()))?;
    let bar = ProgressBar::new(settings.steps);
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
    let mut saved = start_step;
    while step < settings.steps {
        // A new scene every `steps_per_scene` steps (a one-scene dataset is read once).
        if scene.is_none() || (loader.len > 1 && step.is_multiple_of(settings.steps_per_scene)) {
            let s = loader.next().ok_or("the data loader stopped")?.map_err(|e| format!("dataset: {e}"))?;
            let name = s.dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            scene = Some((name, train_scene(gpu, &s)?));
        }
        let (name, data) = scene.as_ref().expect("loaded above");
        step += 1;
        model.lr_scale = cooldown(settings.steps, settings.cooldown, step);
        let losses = match model.train_step(data, step, &mut Autoencoder::step_rng(settings.seed, step)) {
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
            model.save(&checkpoint, Some(&settings))?;
            saved = step;
        }
        // A signal or --stop-at ends the run here; a resumed run goes on as if it had not.
        let signal = interrupt.requested();
        if step < settings.steps && (signal.is_some() || args.stop_at == Some(step)) {
            if saved != step {
                model.save(&checkpoint, Some(&settings))?;
            }
            write_plot(&args.out.join("loss.png"), &log)?;
            bar.abandon();
            if let Some(signal) = signal {
                let message = format!(
                    "{}: stopped after step {step} of {}; checkpoint {} holds step {step} (continue with --resume)",
                    signal_name(signal),
                    settings.steps,
                    checkpoint.display()
                );
                return Err(Interrupted { signal, message }.into());
            }
            break;
        }
    }
    let stopped = step < settings.steps;
    if !stopped {
        model.save(&checkpoint, Some(&settings))?;
        write_plot(&args.out.join("loss.png"), &log)?;
        bar.finish();
    }
    let first = first.expect("at least one step ran");
    let seconds = started.elapsed().as_secs_f64();
    Ok(TrainSummary { model, checkpoint, first, last, seconds, steps: settings.steps, stopped })
}

#[cfg(test)]
mod tests {
    use clap::{CommandFactory, Parser};

    use super::*;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: AutoencoderArgs,
    }

    #[test]
    fn the_help_states_the_library_defaults_of_a_run() {
        // The run settings are options (left out on --resume: the checkpoint's are used), so
        // their defaults are written in the help by hand; they must be RunSettings' own.
        let help = Cli::command().render_long_help().to_string();
        for (option, default) in [
            ("--steps <STEPS>", RunSettings::DEFAULT_STEPS),
            ("--seed <SEED>", RunSettings::DEFAULT_SEED),
            ("--steps-per-scene <STEPS_PER_SCENE>", RunSettings::DEFAULT_STEPS_PER_SCENE),
            ("--cooldown <COOLDOWN>", RunSettings::DEFAULT_COOLDOWN),
        ] {
            let text = &help[help.find(option).expect(option)..];
            let text = &text[..text[option.len()..].find("--").map_or(text.len(), |i| i + option.len())];
            assert!(text.contains(&format!("[default: {default}]")), "{text}");
        }
        let args = Cli::try_parse_from(["train", "--data", "d", "--out", "o", "--seed", "3"]).unwrap().args;
        assert_eq!(args.request(), RunRequest { seed: Some(3), ..Default::default() });
    }
}
