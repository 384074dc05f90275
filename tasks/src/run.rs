//! How a training run starts, for every front end (the `velox train` commands, the demo, the
//! Python package): new, resumed from the run's own checkpoint, or started from another run's
//! parameters ([`Begin`]); the run folder prepared once; the model built, loaded or fitted to
//! the stored tokens it learns from; then the library's trainer
//! (`velox_models::train::trainer::train`). A front end parses its arguments into a
//! [`RunSpec`], shows what the [`Observer`] tells it, and decides how to stop (`stop`).
//!
//! Errors speak of settings as `velox_engine::Error::Setting` does (`{seed}`, `{resume}`), so
//! that each front end names them its own way.
//!
//! Tests: `tools/tests/train_cli.rs` and `tools/tests/models_cli.rs` (through the command
//! line), `python/tests` (through Python).

use std::path::{Path, PathBuf};

use velox_data::DataResult;
use velox_engine::{Error, FileOp, Gpu, Precision};
use velox_models::config::{AutoencoderConfig, GenerationTask, GeneratorConfig, TrackerConfig, VoxelConfig};
use velox_models::model::{is_named_config, Model};
use velox_models::run::RunRequest;
use velox_models::train::collective::Collective;
use velox_models::train::source::SampleSource;
use velox_models::train::trainer::{train, Outcome, RunFolder, TrainOptions};
pub use velox_models::train::trainer::{Begin, Observer, Stop};
use velox_models::velox::autoencoder::Autoencoder;
use velox_models::velox::dinov2::Dinov2;
use velox_models::velox::generator::Generator;
use velox_models::velox::tokens::TokenManifest;
use velox_models::velox::tracker::Tracker;
use velox_models::velox::voxels::VoxelDecoder;

use crate::{GenScenes, SceneFolders, TokenScenes, TrackScenes};

/// The config a new run takes when none is asked for.
pub const DEFAULT_CONFIG: &str = "small";

/// What a run is asked to be: where it lives, how it starts, its model's config and its
/// settings (those left `None` take the library's defaults, or a resumed run's own).
#[derive(Clone, Debug)]
pub struct RunSpec {
    /// The run's folder: checkpoint.safetensors, log.jsonl, loss.png.
    pub out: PathBuf,
    pub begin: Begin,
    /// A config name (`velox_models::model::NAMED_CONFIGS`) or a JSON file; `None`: the
    /// default ([`DEFAULT_CONFIG`]), or with [`Begin::Init`] the config of that checkpoint. A
    /// resumed run keeps its own (with a note when another is asked for).
    pub config: Option<String>,
    /// Seed, steps, steps per scene, cooldown, accumulation, precision. A new run without a
    /// precision takes [`default_training_precision`]'s.
    pub request: RunRequest,
    /// Steps between checkpoints (one is always written at the end).
    pub checkpoint_every: u64,
    /// Steps between redraws of the loss plot.
    pub plot_every: u64,
    /// Stop after this step, as a stop request does.
    pub stop_at: Option<u64>,
    /// Whether a step is recorded while the last runs; `None`: the device's default (on
    /// except on CPU devices; see `Trainer::set_overlap`).
    pub overlap: Option<bool>,
}

impl RunSpec {
    /// The defaults of the command line: a new run in `out`, a checkpoint every 200 steps,
    /// the plot every 25.
    pub fn new(out: &Path) -> RunSpec {
        RunSpec {
            out: out.to_path_buf(),
            begin: Begin::New,
            config: None,
            request: RunRequest::default(),
            checkpoint_every: 200,
            plot_every: 25,
            stop_at: None,
            overlap: None,
        }
    }

    fn options(&self, gpu: &Gpu) -> DataResult<TrainOptions> {
        for (setting, every) in [("checkpoint_every", self.checkpoint_every), ("plot_every", self.plot_every)]
        {
            if every == 0 {
                return Err(Error::setting(setting, format!("{{{setting}}} must be at least 1 step")).into());
            }
        }
        let mut request = self.request.clone();
        if self.begin != Begin::Resume && request.precision.is_none() {
            request.precision = Some(default_training_precision(gpu));
        }
        Ok(TrainOptions {
            out: self.out.clone(),
            begin: self.begin.clone(),
            request,
            checkpoint_every: self.checkpoint_every,
            plot_every: self.plot_every,
            stop_at: self.stop_at,
            prefetch: 2,
            overlap: self.overlap,
        })
    }
}

/// Where a model downstream of the encoder finds its samples: the dataset, the stored tokens
/// of its scenes (`velox encode`), and the autoencoder they must come from.
#[derive(Clone, Debug, Default)]
pub struct TokenData {
    pub data: PathBuf,
    /// Default: DATA/tokens (the tracker's: DATA/tokens-video).
    pub tokens: Option<PathBuf>,
    /// The autoencoder checkpoint the tokens must come from (else the one they record is
    /// checked, if it is still there).
    pub checkpoint: Option<PathBuf>,
}

/// f16 where the device multiplies f16 on cooperative matrices (a GPU's tensor cores; not a
/// CPU device's emulated ones, see `matmul::coop_wanted`), else f32: the portable f16 kernels
/// save memory but not time.
pub fn default_training_precision(gpu: &Gpu) -> Precision {
    match velox_engine::ops::matmul::coop_kernel(gpu.caps()) {
        Some(k) if gpu.supports(k) => Precision::F16,
        _ => Precision::F32,
    }
}

/// The model a run starts from, its folder prepared (once, here): its own checkpoint when it
/// resumes (another config asked for is ignored, with a note); a fresh model of the config
/// asked for, or else of the checkpoint's, when it starts from another run's parameters; a
/// fresh model of the config asked for (`fresh_config(None)`: the default) when it is new.
/// `fresh_config` makes the config of a new model from the name asked for.
pub fn start_run<M: Model>(
    gpu: &Gpu,
    spec: &RunSpec,
    observer: &mut dyn Observer,
    fresh_config: impl Fn(Option<&str>) -> DataResult<M::Config>,
) -> DataResult<M> {
    let folder = RunFolder::new(&spec.out);
    folder.prepare(&spec.begin)?;
    let seed = spec.request.seed.unwrap_or(velox_models::run::RunSettings::DEFAULT_SEED);
    let asked = spec.config.as_deref();
    Ok(match &spec.begin {
        Begin::Resume => {
            if velox_models::checkpoint::peek(&folder.checkpoint)?.weights_only {
                return Err(Error::file(
                    &folder.checkpoint,
                    FileOp::Content,
                    "holds weights only (no optimiser moments): a run resumes from its own checkpoint",
                )
                .into());
            }
            let model = M::load(gpu, &folder.checkpoint)?;
            let kept = model.config_name();
            if let Some(asked) = asked.filter(|&c| c != kept) {
                observer.note(&format!(
                    "resuming the checkpoint's config {kept:?} (the config {asked:?} asked for is ignored)"
                ));
            }
            model
        }
        Begin::Init(from) => {
            velox_models::train::trainer::check_init_kind(from, &M::KIND.into())?;
            let cfg = match asked {
                Some(name) => fresh_config(Some(name))?,
                None => M::checkpoint_config(from)?,
            };
            M::build(gpu, &cfg, seed)?
        }
        Begin::New => M::build(gpu, &fresh_config(asked)?, seed)?,
    })
}

/// Trains the autoencoder on the scenes of `data` (`velox data synth|gltf`), as one of
/// `collective`'s processes (process 0 tells `observer` and writes the run's files). When
/// `stop` says so, the step under way is finished, the checkpoint written, and the outcome
/// says [`Stop::Asked`].
pub fn train_autoencoder<C: Collective>(
    gpu: &Gpu,
    data: &Path,
    spec: &RunSpec,
    observer: &mut dyn Observer,
    stop: &dyn Fn() -> bool,
    collective: &C,
) -> DataResult<Outcome> {
    let fresh = |name: Option<&str>| Ok(AutoencoderConfig::named(name.unwrap_or(DEFAULT_CONFIG))?);
    let mut model: Autoencoder = start_run(gpu, spec, observer, fresh)?;
    let scenes = SceneFolders::open(gpu, data)?;
    run(gpu, &mut model, &scenes, spec, observer, stop, collective)
}

/// Trains the voxel decoder on the stored tokens and occupancy of `data`'s scenes.
pub fn train_voxels<C: Collective>(
    gpu: &Gpu,
    data: &TokenData,
    spec: &RunSpec,
    observer: &mut dyn Observer,
    stop: &dyn Fn() -> bool,
    collective: &C,
) -> DataResult<Outcome> {
    let scenes = TokenScenes::open(gpu, &data.data, data.tokens.as_deref(), data.checkpoint.as_deref())?;
    let mut model: VoxelDecoder = start_token_model(gpu, spec, &scenes, observer, |_| {})?;
    run(gpu, &mut model, &scenes, spec, observer, stop, collective)
}

/// Trains the tracker on the stored tokens of `data`'s RGBD videos and their tracks.
pub fn train_tracker<C: Collective>(
    gpu: &Gpu,
    data: &TokenData,
    spec: &RunSpec,
    observer: &mut dyn Observer,
    stop: &dyn Fn() -> bool,
    collective: &C,
) -> DataResult<Outcome> {
    let scenes = TrackScenes::open(gpu, &data.data, data.tokens.as_deref(), data.checkpoint.as_deref())?;
    let mut model: Tracker = start_token_model(gpu, spec, &scenes.0, observer, |_| {})?;
    run(gpu, &mut model, &scenes, spec, observer, stop, collective)
}

/// Trains the generator for `task` on the stored tokens of `data`'s scenes, conditioned on
/// DINOv2's features when `dinov2` gives its weights (else on the RGB patch embedding alone).
#[allow(clippy::too_many_arguments)]
pub fn train_generator<C: Collective>(
    gpu: &Gpu,
    data: &TokenData,
    task: GenerationTask,
    dinov2: Option<&Path>,
    spec: &RunSpec,
    observer: &mut dyn Observer,
    stop: &dyn Fn() -> bool,
    collective: &C,
) -> DataResult<Outcome> {
    let tokens = TokenScenes::open(gpu, &data.data, data.tokens.as_deref(), data.checkpoint.as_deref())?;
    let dino = match dinov2 {
        Some(path) => Some(Dinov2::load(gpu, path)?),
        None => {
            observer.note("no DINOv2 weights given: the condition is the RGB patch embedding alone");
            None
        }
    };
    let (dino_width, dino_hash) = dino.as_ref().map_or((0, None), |d| (d.config.width, d.file_hash.clone()));
    let mut model: Generator =
        start_token_model(gpu, spec, &tokens, observer, |cfg: &mut GeneratorConfig| {
            cfg.task = task;
            cfg.dino_width = dino_width;
            cfg.dino_hash = dino_hash.clone();
        })?;
    let cfg = &model.cfg;
    if cfg.task != task {
        let message =
            format!("the generator was trained for the {:?} task, not {task:?} ({{task}})", cfg.task);
        return Err(Error::setting("task", message).into());
    }
    if cfg.dino_hash != dino_hash {
        let message = match &cfg.dino_hash {
            Some(h) => format!(
                "the generator was trained on the DINOv2 weights of hash {h}: give them as {{dinov2}}"
            ),
            None => "the generator was trained without DINOv2: leave out {dinov2}".to_string(),
        };
        return Err(Error::setting("dinov2", message).into());
    }
    let source = GenScenes::new(tokens, &model.cfg, dino)?;
    run(gpu, &mut model, &source, spec, observer, stop, collective)
}

/// The config of a model that trains on stored tokens: the token width and autoencoder hash
/// it records.
pub trait TokenModelConfig {
    fn tokens(&mut self) -> (&mut usize, &mut Option<String>);
    /// What else a new config takes from the tokens (the generator: their count, for a named
    /// config, and their statistics).
    fn fit(&mut self, _manifest: &TokenManifest, _named: bool) {}
}

impl TokenModelConfig for GeneratorConfig {
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
    fn tokens(&mut self) -> (&mut usize, &mut Option<String>) {
        (&mut self.token_dim, &mut self.encoder_hash)
    }
}

impl TokenModelConfig for TrackerConfig {
    fn tokens(&mut self) -> (&mut usize, &mut Option<String>) {
        (&mut self.token_dim, &mut self.encoder_hash)
    }
}

/// The model a run on stored tokens starts from ([`start_run`]): a named config takes the
/// tokens' width (and what [`TokenModelConfig::fit`] takes) and records their autoencoder,
/// then `adjust` sets what the caller decides; a model that learned another autoencoder's
/// tokens, or tokens of another width, is refused.
fn start_token_model<M>(
    gpu: &Gpu,
    spec: &RunSpec,
    tokens: &TokenScenes,
    observer: &mut dyn Observer,
    adjust: impl Fn(&mut M::Config),
) -> DataResult<M>
where
    M: Model,
    M::Config: TokenModelConfig,
{
    if let Some(note) = tokens.checkpoint().note() {
        observer.note(note);
    }
    let manifest = tokens.manifest();
    let (token_dim, hash) = (manifest.token_dim, &manifest.origin.checkpoint_hash);
    // A named config takes the tokens' width; a config file must already have it.
    let fresh = |name: Option<&str>| -> DataResult<M::Config> {
        let name = name.unwrap_or(DEFAULT_CONFIG);
        let mut cfg = M::named_config(name)?;
        let named = is_named_config(name);
        let (dim, from) = cfg.tokens();
        if named {
            *dim = token_dim;
        }
        *from = Some(hash.clone());
        cfg.fit(manifest, named);
        adjust(&mut cfg);
        Ok(cfg)
    };
    let mut model: M = start_run(gpu, spec, observer, fresh)?;
    let (dim, from) = model.config_mut().tokens();
    tokens.check_model(M::WHAT, from.as_deref(), *dim)?;
    Ok(model)
}

/// The library's trainer on a started model.
fn run<M, S, C>(
    gpu: &Gpu,
    model: &mut M,
    source: &S,
    spec: &RunSpec,
    observer: &mut dyn Observer,
    stop: &dyn Fn() -> bool,
    collective: &C,
) -> DataResult<Outcome>
where
    M: Model,
    S: SampleSource<Sample = M::Sample>,
    C: Collective,
{
    let options = spec.options(gpu)?;
    Ok(train(model, source, &options, collective, observer, stop)?)
}
