//! `velox train autoencoder|voxels|tracker|generator`: the library's run API
//! (`velox_tasks::run`: how a run starts, new, resumed or from another run's parameters, and
//! the trainer) on a dataset made by `velox data`, with a progress bar, signals and a summary.
//! The command parses its arguments into a `RunSpec` and prints; the run itself (the folder,
//! the model, settings, samples, steps, log, plot, checkpoints, stops) is the library's.

use std::path::PathBuf;

use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use velox_engine::{Gpu, Precision};
use velox_models::config::GenerationTask;
use velox_models::run::{RunRequest, RunSettings};
use velox_models::train::collective::Collective;
use velox_models::train::distributed::Comm;
use velox_models::train::trainer::{Begin, Observer, Outcome, Quiet, StepReport, Stop, TimeSplit};
use velox_tasks::run::{RunSpec, TokenData};

use crate::decode::PrecisionArg;
use crate::interrupt::{signal_name, Interrupt, Interrupted};
use crate::CliResult;

#[derive(Subcommand)]
pub enum TrainCommand {
    /// The autoencoder: encoder, 4D surface decoder and Gaussian decoder, on L_V + L_GS + 1e-4 L_C.
    ///
    /// Ctrl-C (SIGINT) or SIGTERM finishes the step under way, writes the checkpoint and exits
    /// with 130 (SIGINT) or 143 (SIGTERM), naming the checkpoint; --resume continues from it. A
    /// second signal quits at once, leaving the previous checkpoint whole.
    Autoencoder(AutoencoderArgs),
    /// The voxel decoder: the occupied voxels of each frame from the stored tokens of a
    /// trained encoder (`velox encode`), the encoder frozen. The same run options, stops and
    /// resumes as `train autoencoder`.
    Voxels(TokenModelArgs),
    /// The 3D tracker: each query's position at every frame from the stored tokens of the
    /// scenes' RGBD videos (`velox encode --source video`), the encoder frozen. The same run
    /// options, stops and resumes as `train autoencoder`.
    Tracker(TokenModelArgs),
    /// The generator (video-to-4D, or image-to-4D with --task image): a DiT that makes the
    /// tokens of a scene from its conditioning video, trained by rectified flow on the stored
    /// tokens (`velox encode`), normalised by their statistics. The same run options, stops
    /// and resumes as `train autoencoder`.
    Generator(GeneratorArgs),
}

/// `velox train generator`: a model on stored tokens, its task, and DINOv2.
#[derive(Args, Clone)]
pub struct GeneratorArgs {
    #[command(flatten)]
    pub model: TokenModelArgs,
    /// What the generator is conditioned on: the scenes' 24-frame videos, or their first frame.
    #[arg(long, value_enum, default_value_t = TaskArg::Video)]
    pub task: TaskArg,
    /// DINOv2 weights (safetensors in the Hugging Face `facebook/dinov2-large` layout, with its
    /// config.json beside it if it is another size): the condition then holds DINOv2's patch
    /// features; without them it holds the RGB patch embedding alone.
    #[arg(long, value_name = "FILE")]
    pub dinov2: Option<PathBuf>,
}

/// `--task` of the generator commands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TaskArg {
    Video,
    Image,
}

impl From<TaskArg> for GenerationTask {
    fn from(t: TaskArg) -> GenerationTask {
        match t {
            TaskArg::Video => GenerationTask::Video,
            TaskArg::Image => GenerationTask::Image,
        }
    }
}

#[derive(Args, Clone)]
pub struct AutoencoderArgs {
    /// Dataset folder (scenes written by `velox data synth` or `velox data gltf`).
    #[arg(long)]
    pub data: PathBuf,
    /// Model sizes: paper, small, tiny, or a JSON config file [default: small; with --init, the
    /// config of that checkpoint].
    #[arg(long)]
    pub config: Option<String>,
    #[command(flatten)]
    pub run: RunArgs,
}

/// The options of a model that trains on stored tokens with the encoder frozen (the voxel
/// decoder, the tracker).
#[derive(Args, Clone)]
pub struct TokenModelArgs {
    /// Dataset folder: its scenes' occupancy (voxel decoder) or video tracks (tracker) are
    /// what the model learns.
    #[arg(long)]
    pub data: PathBuf,
    /// The scenes' stored tokens (`velox encode`) [default: DATA/tokens; the tracker's,
    /// DATA/tokens-video, from `velox encode --source video`].
    #[arg(long)]
    pub tokens: Option<PathBuf>,
    /// The autoencoder checkpoint the tokens must come from (else the one they record is
    /// checked, if it is still there).
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// The model's sizes: paper, small, tiny, or a JSON config file [default: small; with
    /// --init, the config of that checkpoint]. Its token width is the tokens'.
    #[arg(long)]
    pub config: Option<String>,
    #[command(flatten)]
    pub run: RunArgs,
}

/// The options every `velox train` command shares: the run's folder, length, seed, batches,
/// checkpoints and stops.
#[derive(Args, Clone)]
pub struct RunArgs {
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
    /// started with (seed, steps per scene, cooldown, batch, total steps), so that it repeats
    /// the uninterrupted run exactly. A --seed, --steps-per-scene, --cooldown or --accumulate
    /// that changes the run, or a dataset whose scenes changed, is refused; --steps sets a new
    /// total.
    #[arg(long, conflicts_with = "init")]
    pub resume: bool,
    /// Start a new run from the parameters of another run's checkpoint (step 0, fresh
    /// optimiser moments): fine-tuning. The model's config is that checkpoint's unless
    /// --config names one whose parameters have the same shapes.
    #[arg(long, value_name = "CHECKPOINT")]
    pub init: Option<PathBuf>,
    /// Steps on the same scenes before the next ones are loaded [default: 8].
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps_per_scene: Option<u64>,
    /// Micro-batches (of the config's `batch` scenes each) accumulated into one optimiser
    /// step: any batch on any device, at the memory of one micro-batch [default: 1].
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=65536))]
    pub accumulate: Option<u64>,
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
    /// Precision of the training passes: f32, or f16 (the products of linear layers and
    /// attention read f16 operands and accumulate in f32, forward and backward; f32 master
    /// weights and optimiser moments; the loss scaled dynamically, a step that overflows skipped
    /// and run again at half the scale) [default: f16 where a GPU has cooperative matrices,
    /// else f32 (lavapipe's are emulated); a resumed run keeps its own].
    #[arg(long, value_enum)]
    pub precision: Option<PrecisionArg>,
    /// Record each step (each micro-batch) while the last one runs on the device, so that the
    /// device does not wait for the recording (one process): the same steps to the bit, with
    /// two micro-batches' activations in memory at once [default: on, except on a CPU device,
    /// where recording would take cores from the device's work].
    #[arg(long, value_enum)]
    pub overlap: Option<OnOff>,
}

/// A switch given on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum OnOff {
    On,
    Off,
}

impl RunArgs {
    /// The run settings the command line gives (`None` where it leaves one out: the library's
    /// defaults, or a resumed run's own).
    fn request(&self) -> RunRequest {
        RunRequest {
            seed: self.seed,
            steps: self.steps,
            steps_per_scene: self.steps_per_scene,
            cooldown: self.cooldown,
            accumulate: self.accumulate,
            precision: self.precision.map(Precision::from),
        }
    }

    /// The run the command asks for, of the model config `config`.
    pub fn spec(&self, config: Option<&str>) -> RunSpec {
        RunSpec {
            out: self.out.clone(),
            begin: self.begin(),
            config: config.map(str::to_string),
            request: self.request(),
            checkpoint_every: self.checkpoint_every,
            plot_every: self.plot_every,
            stop_at: self.stop_at,
            overlap: self.overlap.map(|o| o == OnOff::On),
        }
    }

    fn begin(&self) -> Begin {
        match (&self.init, self.resume) {
            (Some(from), _) => Begin::Init(from.clone()),
            (None, true) => Begin::Resume,
            (None, false) => Begin::New,
        }
    }
}

pub fn run(cmd: TrainCommand) -> CliResult<()> {
    // One process, or one of an MPI run's (`mpirun -np N velox train ...`, built with the
    // feature `mpi`): each takes its own GPU and its share of every step.
    let comm = Comm::world()?;
    let interrupt = Interrupt::catch()?;
    let gpu = if comm.size() > 1 { Gpu::for_local_rank(comm.local_rank())? } else { Gpu::new()? };
    let (outcome, out) = match &cmd {
        TrainCommand::Autoencoder(args) => (train_autoencoder(&gpu, args, &interrupt, &comm), &args.run.out),
        TrainCommand::Voxels(args) => (train_voxels(&gpu, args, &interrupt, &comm), &args.run.out),
        TrainCommand::Tracker(args) => (train_tracker(&gpu, args, &interrupt, &comm), &args.run.out),
        TrainCommand::Generator(args) => {
            (train_generator(&gpu, args, &interrupt, &comm), &args.model.run.out)
        }
    };
    let o = match outcome {
        Ok(o) => o,
        // A stop ends every process alike (they agree on it before it happens); an error of
        // one process must end the others, which could wait for it forever.
        Err(e) if comm.size() > 1 && e.downcast_ref::<Interrupted>().is_none() => {
            eprintln!("error on process {} of {}: {}", comm.rank(), comm.size(), crate::message(&*e));
            comm.abort_all(1)
        }
        Err(e) => return Err(e),
    };
    if !comm.is_root() {
        return Ok(());
    }
    let step = o.last.step;
    if o.stopped.is_some() {
        println!(
            "stopped after step {step} of {} as --stop-at asks: checkpoint {} holds it (continue with --resume)",
            o.settings.steps,
            o.checkpoint.display()
        );
    } else {
        println!(
            "trained {step} steps in {:.0} s: loss {:.4} -> {:.4}; checkpoint {}, log and loss plot in {}",
            o.seconds,
            o.first.losses.total(),
            o.last.losses.total(),
            o.checkpoint.display(),
            out.display()
        );
    }
    println!(
        "{:.2} samples/s ({} a step); a step: {}",
        o.samples_per_second,
        o.settings.global_batch,
        split_text(&o.time)
    );
    Ok(())
}

/// "data 0.001 s, compute 0.31 s, ..." for a time split.
pub fn split_text(t: &TimeSplit) -> String {
    let passes = match (t.forward, t.backward) {
        (Some(f), Some(b)) => format!("forward {f:.3} s, backward {b:.3} s, "),
        _ => String::new(),
    };
    format!(
        "data {:.3} s, {passes}compute {:.3} s, all-reduce {:.3} s, optimiser {:.3} s (total {:.3} s)",
        t.data,
        t.compute,
        t.all_reduce,
        t.optimiser,
        t.total()
    )
}

/// The progress bar of a run, and its notes on stderr.
#[derive(Default)]
struct Progress {
    bar: Option<ProgressBar>,
}

impl Observer for Progress {
    fn note(&mut self, text: &str) {
        match &self.bar {
            Some(bar) => bar.suspend(|| eprintln!("note: {text}")),
            None => eprintln!("note: {text}"),
        }
    }

    fn begin(&mut self, settings: &RunSettings, start_step: u64) {
        let bar = ProgressBar::new(settings.steps);
        bar.set_position(start_step);
        bar.set_style(
            ProgressStyle::with_template("{bar:30} {pos}/{len} steps  {elapsed} (eta {eta})  {msg}")
                .expect("a valid template"),
        );
        self.bar = Some(bar);
    }

    fn step(&mut self, r: &StepReport, samples_per_second: f64) {
        let Some(bar) = &self.bar else { return };
        let terms: Vec<String> = r.losses.terms.iter().skip(1).map(|(n, v)| format!("{n} {v:.5}")).collect();
        bar.set_message(format!(
            "loss {:.4} ({})  {samples_per_second:.2} samples/s",
            r.losses.total(),
            terms.join(", ")
        ));
        bar.set_position(r.step);
    }

    fn end(&mut self, completed: bool) {
        if let Some(bar) = self.bar.take() {
            if completed {
                bar.finish();
            } else {
                bar.abandon();
            }
        }
    }
}

/// Trains as the command does (also used by the demo), as one of `collective`'s processes:
/// process 0 shows the progress and writes the run's files. When `interrupt` asks for a stop,
/// the step under way is finished, the checkpoint written, and [`Interrupted`] returned.
pub fn train_autoencoder<C: Collective>(
    gpu: &Gpu,
    args: &AutoencoderArgs,
    interrupt: &Interrupt,
    collective: &C,
) -> CliResult<Outcome> {
    let spec = args.run.spec(args.config.as_deref());
    with_progress(interrupt, collective, |observer, stop| {
        velox_tasks::run::train_autoencoder(gpu, &args.data, &spec, observer, stop, collective)
    })
}

/// Trains the voxel decoder as `velox train voxels` does, as one of `collective`'s processes.
pub fn train_voxels<C: Collective>(
    gpu: &Gpu,
    args: &TokenModelArgs,
    interrupt: &Interrupt,
    collective: &C,
) -> CliResult<Outcome> {
    let spec = args.run.spec(args.config.as_deref());
    with_progress(interrupt, collective, |observer, stop| {
        velox_tasks::run::train_voxels(gpu, &args.token_data(), &spec, observer, stop, collective)
    })
}

/// Trains the tracker as `velox train tracker` does, as one of `collective`'s processes.
pub fn train_tracker<C: Collective>(
    gpu: &Gpu,
    args: &TokenModelArgs,
    interrupt: &Interrupt,
    collective: &C,
) -> CliResult<Outcome> {
    let spec = args.run.spec(args.config.as_deref());
    with_progress(interrupt, collective, |observer, stop| {
        velox_tasks::run::train_tracker(gpu, &args.token_data(), &spec, observer, stop, collective)
    })
}

/// Trains the generator as `velox train generator` does, as one of `collective`'s processes.
pub fn train_generator<C: Collective>(
    gpu: &Gpu,
    args: &GeneratorArgs,
    interrupt: &Interrupt,
    collective: &C,
) -> CliResult<Outcome> {
    let m = &args.model;
    let spec = m.run.spec(m.config.as_deref());
    let (task, dinov2) = (args.task.into(), args.dinov2.as_deref());
    with_progress(interrupt, collective, |observer, stop| {
        velox_tasks::run::train_generator(
            gpu,
            &m.token_data(),
            task,
            dinov2,
            &spec,
            observer,
            stop,
            collective,
        )
    })
}

impl TokenModelArgs {
    fn token_data(&self) -> TokenData {
        TokenData {
            data: self.data.clone(),
            tokens: self.tokens.clone(),
            checkpoint: self.checkpoint.clone(),
        }
    }
}

/// A run of the library's with the command's progress bar, signals and stop message.
fn with_progress<C: Collective>(
    interrupt: &Interrupt,
    collective: &C,
    run: impl FnOnce(&mut dyn Observer, &dyn Fn() -> bool) -> velox_data::DataResult<Outcome>,
) -> CliResult<Outcome> {
    let stop = || interrupt.requested().is_some();
    let mut progress = Progress::default();
    let observer: &mut dyn Observer = if collective.is_root() { &mut progress } else { &mut Quiet };
    let outcome = run(observer, &stop)?;
    if outcome.stopped == Some(Stop::Asked) {
        let signal = interrupt.requested().expect("the stop was asked for by a signal");
        let step = outcome.last.step;
        let message = format!(
            "{}: stopped after step {step} of {}; checkpoint {} holds step {step} (continue with --resume)",
            signal_name(signal),
            outcome.settings.steps,
            outcome.checkpoint.display()
        );
        return Err(Interrupted { signal, message }.into());
    }
    Ok(outcome)
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
            ("--accumulate <ACCUMULATE>", RunSettings::DEFAULT_ACCUMULATE),
        ] {
            let text = &help[help.find(option).expect(option)..];
            let text = &text[..text[option.len()..].find("--").map_or(text.len(), |i| i + option.len())];
            assert!(text.contains(&format!("[default: {default}]")), "{text}");
        }
        let args = Cli::try_parse_from(["train", "--data", "d", "--out", "o", "--seed", "3"]).unwrap().args;
        let precision = Some(Precision::F16);
        assert_eq!(args.run.request(), RunRequest { seed: Some(3), ..Default::default() });
        let args = Cli::try_parse_from(["train", "--data", "d", "--out", "o", "--resume"]).unwrap().args;
        assert_eq!(args.run.request().precision, None, "a resumed run keeps its precision");
        let args =
            Cli::try_parse_from(["train", "--data", "d", "--out", "o", "--precision", "f16"]).unwrap().args;
        assert_eq!(args.run.request().precision, precision);
        assert_eq!(args.run.begin(), Begin::New);
        let both = Cli::try_parse_from(["train", "--data", "d", "--out", "o", "--resume", "--init", "c"]);
        assert!(both.is_err(), "--resume and --init exclude each other");
    }
}
