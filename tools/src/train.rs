//! `velox train autoencoder`: the library's trainer (`velox_models::train::trainer`) on a
//! dataset made by `velox data`, with a progress bar and a summary. The command parses, builds
//! the model (new, from another run's weights, or the checkpoint to resume), and prints; the
//! run itself (settings, samples, steps, log, plot, checkpoints, stops) is the library's.

use std::path::{Path, PathBuf};

use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use velox_engine::{Gpu, Precision};
use velox_models::config::{AutoencoderConfig, GenerationTask, GeneratorConfig, TrackerConfig, VoxelConfig};
use velox_models::run::{RunRequest, RunSettings};
use velox_models::train::collective::Collective;
use velox_models::train::distributed::Comm;
use velox_models::train::source::SampleSource;
use velox_models::train::trainer::{
    train, Begin, Observer, Outcome, Quiet, RunFolder, StepReport, Stop, TimeSplit, TrainOptions,
};
use velox_models::train::Trainable;
use velox_models::velox::autoencoder::Autoencoder;
use velox_models::velox::dinov2::Dinov2;
use velox_models::velox::generator::Generator;
use velox_models::velox::tokens::TokenManifest;
use velox_models::velox::tracker::Tracker;
use velox_models::velox::voxels::VoxelDecoder;
use velox_tasks::{GenScenes, SceneFolders, TokenScenes, TrackScenes};

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
    /// and run again at half the scale) [default: f16 where the device has cooperative
    /// matrices, else f32; a resumed run keeps its own].
    #[arg(long, value_enum)]
    pub precision: Option<PrecisionArg>,
}

impl RunArgs {
    /// The run settings the command line gives (`None` where it leaves one out; a new run
    /// without --precision takes `default_precision`, the device's).
    fn request(&self, default_precision: Precision) -> RunRequest {
        let default = (!self.resume).then_some(default_precision);
        RunRequest {
            seed: self.seed,
            steps: self.steps,
            steps_per_scene: self.steps_per_scene,
            cooldown: self.cooldown,
            accumulate: self.accumulate,
            precision: self.precision.map(Precision::from).or(default),
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
            eprintln!("error on process {} of {}: {e}", comm.rank(), comm.size());
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
    let run = &args.run;
    let begin = run.begin();
    let folder = RunFolder::new(&run.out);
    folder.prepare(&begin)?;
    let scenes = SceneFolders::open(gpu, &args.data)?;
    let seed = run.seed.unwrap_or(RunSettings::DEFAULT_SEED);
    let named = |name: Option<&str>| Ok(AutoencoderConfig::named(name.unwrap_or("small"))?);
    let mut model: Autoencoder = starting_model(gpu, &begin, &folder, args.config.as_deref(), seed, named)?;
    run_training(&mut model, &scenes, run, begin, interrupt, collective)
}

/// Trains the voxel decoder as `velox train voxels` does, as one of `collective`'s processes.
pub fn train_voxels<C: Collective>(
    gpu: &Gpu,
    args: &TokenModelArgs,
    interrupt: &Interrupt,
    collective: &C,
) -> CliResult<Outcome> {
    let scenes = TokenScenes::open(gpu, &args.data, args.tokens.as_deref(), args.checkpoint.as_deref())?;
    train_on_tokens::<VoxelDecoder, _, _>(gpu, args, &scenes, &scenes, interrupt, collective)
}

/// Trains the tracker as `velox train tracker` does, as one of `collective`'s processes.
pub fn train_tracker<C: Collective>(
    gpu: &Gpu,
    args: &TokenModelArgs,
    interrupt: &Interrupt,
    collective: &C,
) -> CliResult<Outcome> {
    let scenes = TrackScenes::open(gpu, &args.data, args.tokens.as_deref(), args.checkpoint.as_deref())?;
    train_on_tokens::<Tracker, _, _>(gpu, args, &scenes, &scenes.0, interrupt, collective)
}

/// Trains the generator as `velox train generator` does, as one of `collective`'s processes.
pub fn train_generator<C: Collective>(
    gpu: &Gpu,
    args: &GeneratorArgs,
    interrupt: &Interrupt,
    collective: &C,
) -> CliResult<Outcome> {
    let m = &args.model;
    let tokens = TokenScenes::open(gpu, &m.data, m.tokens.as_deref(), m.checkpoint.as_deref())?;
    let dino = match &args.dinov2 {
        Some(path) => Some(Dinov2::load(gpu, path)?),
        None => {
            eprintln!("note: no DINOv2 weights (--dinov2): the condition is the RGB patch embedding alone");
            None
        }
    };
    let task: GenerationTask = args.task.into();
    let (dino_width, dino_hash) = dino.as_ref().map_or((0, None), |d| (d.config.width, d.file_hash.clone()));
    let model: Generator = start_token_model(gpu, m, &tokens, |cfg: &mut GeneratorConfig| {
        cfg.task = task;
        cfg.dino_width = dino_width;
        cfg.dino_hash = dino_hash.clone();
    })?;
    let cfg = &model.cfg;
    if cfg.task != task {
        return Err(format!(
            "the generator was trained for the {:?} task, not {:?} (--task)",
            cfg.task, task
        )
        .into());
    }
    if cfg.dino_hash != dino_hash {
        return Err(match &cfg.dino_hash {
            Some(h) => format!(
                "the generator was trained on the DINOv2 weights of hash {h}: give them with --dinov2"
            ),
            None => "the generator was trained without DINOv2: leave out --dinov2".to_string(),
        }
        .into());
    }
    let source = GenScenes::new(tokens, cfg, dino)?;
    let mut model = model;
    run_training(&mut model, &source, &m.run, m.run.begin(), interrupt, collective)
}

/// The config of a model that trains on stored tokens: its name for messages, and the token
/// width and autoencoder hash it records.
trait TokenModelConfig: Sized {
    const WHAT: &'static str;
    fn named(name: &str) -> velox_engine::Result<Self>;
    fn tokens(&mut self) -> (&mut usize, &mut Option<String>);
    /// What else a new config takes from the tokens (the generator: their count, for a named
    /// config, and their statistics).
    fn fit(&mut self, _manifest: &TokenManifest, _named: bool) {}
}

impl TokenModelConfig for GeneratorConfig {
    const WHAT: &'static str = "generator";
    fn named(name: &str) -> velox_engine::Result<Self> {
        GeneratorConfig::named(name)
    }
    fn tokens(&mut self) -> (&mut usize, &mut Option<String>) {
        (&mut self.token_dim, &mut self.encoder_hash)
    }
    fn fit(&mut self, manifest: &TokenManifest, named: bool) {
        if named {
            self.tokens = manifest.tokens;
        }
        self.token_mean = manifest.mean.iter().map(|&v| v as f32).collect();
        // A channel that never varies keeps a deviation of 1 (it normalises to its offset).
        self.token_std = manifest.std.iter().map(|&v| if v > 0.0 { v as f32 } else { 1.0 }).collect();
    }
}

impl TokenModelConfig for VoxelConfig {
    const WHAT: &'static str = "voxel decoder";
    fn named(name: &str) -> velox_engine::Result<Self> {
        VoxelConfig::named(name)
    }
    fn tokens(&mut self) -> (&mut usize, &mut Option<String>) {
        (&mut self.token_dim, &mut self.encoder_hash)
    }
}

impl TokenModelConfig for TrackerConfig {
    const WHAT: &'static str = "tracker";
    fn named(name: &str) -> velox_engine::Result<Self> {
        TrackerConfig::named(name)
    }
    fn tokens(&mut self) -> (&mut usize, &mut Option<String>) {
        (&mut self.token_dim, &mut self.encoder_hash)
    }
}

/// A run of a model downstream of the encoder on `source` (whose tokens are `tokens`').
fn train_on_tokens<M, S, C>(
    gpu: &Gpu,
    args: &TokenModelArgs,
    source: &S,
    tokens: &TokenScenes,
    interrupt: &Interrupt,
    collective: &C,
) -> CliResult<Outcome>
where
    M: RunModel + Trainable,
    M::Config: TokenModelConfig,
    S: SampleSource<Sample = M::Sample>,
    C: Collective,
{
    let mut model: M = start_token_model(gpu, args, tokens, |_| {})?;
    run_training(&mut model, source, &args.run, args.run.begin(), interrupt, collective)
}

/// The model a run on stored tokens starts from, its folder prepared: a named config takes
/// the tokens' width (and what [`TokenModelConfig::fit`] takes) and records their
/// autoencoder, then `adjust` sets what the command decides; a model that learned another
/// autoencoder's tokens, or tokens of another width, is refused.
fn start_token_model<M>(
    gpu: &Gpu,
    args: &TokenModelArgs,
    tokens: &TokenScenes,
    adjust: impl Fn(&mut M::Config),
) -> CliResult<M>
where
    M: RunModel,
    M::Config: TokenModelConfig,
{
    let run = &args.run;
    let begin = run.begin();
    let folder = RunFolder::new(&run.out);
    folder.prepare(&begin)?;
    if let Some(note) = tokens.checkpoint().note() {
        eprintln!("note: {note}");
    }
    let manifest = tokens.manifest();
    let (token_dim, hash) = (manifest.token_dim, &manifest.origin.checkpoint_hash);
    let seed = run.seed.unwrap_or(RunSettings::DEFAULT_SEED);
    // A named config takes the tokens' width; a config file must already have it.
    let named = |name: Option<&str>| -> CliResult<M::Config> {
        let name = name.unwrap_or("small");
        let mut cfg = M::Config::named(name)?;
        let is_named = matches!(name, "paper" | "small" | "tiny");
        let (dim, from) = cfg.tokens();
        if is_named {
            *dim = token_dim;
        }
        *from = Some(hash.clone());
        cfg.fit(manifest, is_named);
        adjust(&mut cfg);
        Ok(cfg)
    };
    let mut model: M = starting_model(gpu, &begin, &folder, args.config.as_deref(), seed, named)?;
    let (dim, from) = model.config_mut().tokens();
    tokens.check_model(<M::Config as TokenModelConfig>::WHAT, from.as_deref(), *dim)?;
    Ok(model)
}

/// What a run needs of a model to start it: load a checkpoint, read a checkpoint's config,
/// build a fresh model of a config.
trait RunModel: Sized {
    type Config;
    fn load(gpu: &Gpu, checkpoint: &Path) -> velox_engine::Result<Self>;
    fn checkpoint_config(checkpoint: &Path) -> velox_engine::Result<Self::Config>;
    fn fresh(gpu: &Gpu, cfg: &Self::Config, seed: u64) -> velox_engine::Result<Self>;
    fn config_name(&self) -> &str;
    fn config_mut(&mut self) -> &mut Self::Config;
}

/// [`RunModel`] for a model whose `load`, `checkpoint_config` and `new` have the usual
/// signatures and whose config has a `name`.
macro_rules! run_model {
    ($model:ty, $config:ty) => {
        impl RunModel for $model {
            type Config = $config;
            fn load(gpu: &Gpu, checkpoint: &Path) -> velox_engine::Result<Self> {
                <$model>::load(gpu, checkpoint)
            }
            fn checkpoint_config(checkpoint: &Path) -> velox_engine::Result<$config> {
                <$model>::checkpoint_config(checkpoint)
            }
            fn fresh(gpu: &Gpu, cfg: &$config, seed: u64) -> velox_engine::Result<Self> {
                <$model>::new(gpu, cfg, seed)
            }
            fn config_name(&self) -> &str {
                &self.cfg.name
            }
            fn config_mut(&mut self) -> &mut $config {
                &mut self.cfg
            }
        }
    };
}

run_model!(Autoencoder, AutoencoderConfig);
run_model!(VoxelDecoder, VoxelConfig);
run_model!(Tracker, TrackerConfig);
run_model!(Generator, GeneratorConfig);

/// The model a run starts from: its own checkpoint when it resumes (the config asked for, if
/// another, is ignored with a note); a fresh model of the config asked for, or else of the
/// checkpoint's, when it starts from another run's parameters; a fresh model of the config
/// asked for (`named(None)`: the default) when it is new.
fn starting_model<M: RunModel>(
    gpu: &Gpu,
    begin: &Begin,
    folder: &RunFolder,
    asked: Option<&str>,
    seed: u64,
    named: impl Fn(Option<&str>) -> CliResult<M::Config>,
) -> CliResult<M> {
    Ok(match begin {
        Begin::Resume => {
            if velox_models::checkpoint::peek(&folder.checkpoint)?.weights_only {
                return Err(velox_engine::Error::file(
                    &folder.checkpoint,
                    velox_engine::FileOp::Content,
                    "holds weights only (no optimiser moments): --resume needs the run's checkpoint",
                )
                .into());
            }
            let m = M::load(gpu, &folder.checkpoint)?;
            note_resumed_config(m.config_name(), asked);
            m
        }
        Begin::Init(from) => {
            let cfg = match asked {
                Some(name) => named(Some(name))?,
                None => M::checkpoint_config(from)?,
            };
            M::fresh(gpu, &cfg, seed)?
        }
        Begin::New => M::fresh(gpu, &named(asked)?, seed)?,
    })
}

/// f16 where the device multiplies f16 on cooperative matrices (tensor cores), else f32: the
/// portable f16 kernels save memory but not time.
pub fn default_training_precision(gpu: &Gpu) -> Precision {
    match velox_engine::ops::matmul::coop_kernel(gpu.caps()) {
        Some(k) if gpu.supports(k) => Precision::F16,
        _ => Precision::F32,
    }
}

fn note_resumed_config(kept: &str, asked: Option<&str>) {
    if let Some(asked) = asked.filter(|&c| c != kept) {
        eprintln!("note: resuming the checkpoint's config {kept:?} (--config {asked:?} is ignored)");
    }
}

/// The library's trainer with the command's progress bar, signals and stop message.
fn run_training<M, S, C>(
    model: &mut M,
    source: &S,
    run: &RunArgs,
    begin: Begin,
    interrupt: &Interrupt,
    collective: &C,
) -> CliResult<Outcome>
where
    M: Trainable,
    S: SampleSource<Sample = M::Sample>,
    C: Collective,
{
    let options = TrainOptions {
        out: run.out.clone(),
        begin,
        request: run.request(default_training_precision(model.store().flat_params().gpu())),
        checkpoint_every: run.checkpoint_every,
        plot_every: run.plot_every,
        stop_at: run.stop_at,
        prefetch: 2,
    };
    let stop = || interrupt.requested().is_some();
    let mut progress = Progress::default();
    let observer: &mut dyn Observer = if collective.is_root() { &mut progress } else { &mut Quiet };
    let outcome = train(model, source, &options, collective, observer, &stop)?;
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
        assert_eq!(
            args.run.request(Precision::F16),
            RunRequest { seed: Some(3), precision, ..Default::default() }
        );
        let args = Cli::try_parse_from(["train", "--data", "d", "--out", "o", "--resume"]).unwrap().args;
        assert_eq!(args.run.request(Precision::F16).precision, None, "a resumed run keeps its precision");
        let args =
            Cli::try_parse_from(["train", "--data", "d", "--out", "o", "--precision", "f32"]).unwrap().args;
        assert_eq!(args.run.request(Precision::F16).precision, Some(Precision::F32));
        assert_eq!(args.run.begin(), Begin::New);
        let both = Cli::try_parse_from(["train", "--data", "d", "--out", "o", "--resume", "--init", "c"]);
        assert!(both.is_err(), "--resume and --init exclude each other");
    }
}
