//! `velox eval tracking`: a tracker's TAPVid-3D metrics (`velox_models::eval::tracking`).
//! `velox eval recon`: reconstruction quality of a trained autoencoder on held-out scenes
//! (PSNR, SSIM, Chamfer), measured by `velox_models::eval::recon` (its docs give the
//! protocol). The command reads the scenes, writes `eval.json` (every number) and the chosen
//! side-by-side PNGs (ground truth | ours) per scene, and prints a table.

use std::path::{Path, PathBuf};

use indicatif::ProgressBar;
use serde::Serialize;
use velox_engine::Gpu;
use velox_io::image::write_png;
use velox_io::write_bytes;
use velox_models::eval::recon::{evaluate, frames, ReconObserver, ReconOptions, ReconReport};
use velox_models::eval::voxels::{projections, VoxelMetrics};
use velox_models::train::source::SampleSource;
use velox_models::velox::autoencoder::Autoencoder;
use velox_models::velox::decode::{Sampling, VoxelSource};
use velox_models::velox::tracker::Tracker;
use velox_models::velox::voxels::{VoxelDecoder, FRAME_WORDS};
use velox_models::Model;
use velox_tasks::evaluate::ClothTokens;
use velox_tasks::generate::GeneratorModels;
use velox_tasks::{SceneFolders, TokenScenes, TrackScenes};

use crate::decode::{progress, voxel_decoder, PrecisionArg, SamplerArg, VoxelArg};
use crate::overlay::{clip_gif, splat_points};
use crate::CliResult;

#[derive(clap::Subcommand)]
pub enum EvalCommand {
    /// PSNR, SSIM and Chamfer of decoded scenes against their ground truth.
    Recon(ReconArgs),
    /// Accuracy, precision, recall and IoU of a voxel decoder's occupied voxels against the
    /// scenes' occupancy, from their stored tokens (`velox encode`).
    Voxels(VoxelEvalArgs),
    /// TAPVid-3D's metrics (L2, APD, AJ, OA) of a tracker on held-out scenes, from the stored
    /// tokens of their videos (`velox encode --source video`), beside the static baseline and
    /// the truth.
    Tracking(TrackingEvalArgs),
    /// PSNR and SSIM of a generator's scenes on the conditioning view and novel views, beside
    /// those of the encoder's tokens of the same scenes (what the generator learned to make).
    Generation(GenerationEvalArgs),
    /// The physics of an image-to-4D generator on cloth scenes (`velox data cloth`): the
    /// centre of mass of the decoded points per frame against the simulation's, RMSE along
    /// gravity, with plots of height, velocity and acceleration (`eval generation` gives the
    /// image metrics).
    Cloth(ClothEvalArgs),
    /// TAPVid-3D's metrics of any tracker's predictions against the benchmark's own clips, as
    /// its evaluation computes them (`velox_tasks::tapvid3d`): each ground-truth `.npz`
    /// (tracks_XYZ, visibility, queries_xyt, fx_fy_cx_cy, images_jpeg_bytes) against the
    /// prediction `.npz` of the same name (tracks_XYZ [T, N, 3] and visibility [T, N]).
    Tapvid3d(Tapvid3dArgs),
}

#[derive(clap::Args)]
pub struct Tapvid3dArgs {
    /// The benchmark's clips: .npz files, or folders of them.
    #[arg(required = true)]
    ground_truth: Vec<PathBuf>,
    /// The predictions: a folder holding an .npz of each clip's file name, or one .npz when
    /// one clip is scored.
    #[arg(long)]
    predictions: PathBuf,
    /// Depth scalings, comma-separated: median (the benchmark's default), none, mean,
    /// per_trajectory, local_neighborhood, reproduce_2d, median_on_queries.
    #[arg(long, default_value = "median", value_delimiter = ',')]
    scaling: Vec<String>,
    /// Also write every clip's metrics and the means to this JSON file.
    #[arg(long)]
    out: Option<PathBuf>,
}

/// What both evaluations of a generator take: the generator, its autoencoder and DINOv2, the
/// scenes with their stored tokens, and how to generate.
#[derive(clap::Args)]
pub struct GeneratorEvalArgs {
    /// Dataset folder (scenes with their conditioning videos and supervision views; for `eval
    /// cloth`, cloth scenes with their cloth.json).
    #[arg(long)]
    data: PathBuf,
    /// Generator checkpoint (`velox train generator`).
    #[arg(long)]
    checkpoint: PathBuf,
    /// The autoencoder whose tokens the generator learned: it decodes both token sets.
    #[arg(long)]
    autoencoder: PathBuf,
    /// The scenes' stored tokens of that autoencoder [default: DATA/tokens]: decoded the same
    /// way as the generated ones, they give the ceiling.
    #[arg(long)]
    tokens: Option<PathBuf>,
    /// DINOv2 weights, when the generator was trained with them.
    #[arg(long, value_name = "FILE")]
    dinov2: Option<PathBuf>,
    /// Sampler steps, sampler, guidance and seed of the generation.
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u64).range(1..=10_000))]
    steps: u64,
    #[arg(long, value_enum, default_value_t = SamplerArg::Euler)]
    sampler: SamplerArg,
    #[arg(long, default_value_t = 3.0)]
    guidance: f32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Evaluate only the first N scenes (in name order).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    scenes: Option<u64>,
}

/// A generator's evaluation, ready: its models, the scenes, how many are evaluated, and the
/// generation.
struct GeneratorEval {
    models: GeneratorModels,
    scenes: TokenScenes,
    count: usize,
    spec: velox_models::velox::generator::GenerateSpec,
}

impl GeneratorEvalArgs {
    fn open(&self, gpu: &Gpu, out: &std::path::Path) -> CliResult<GeneratorEval> {
        let models = GeneratorModels::load(gpu, &self.checkpoint, &self.autoencoder, self.dinov2.as_deref())?;
        let scenes = TokenScenes::open(gpu, &self.data, self.tokens.as_deref(), Some(&self.autoencoder))?;
        let cfg = &models.generator.cfg;
        scenes.check_model("generator", cfg.encoder_hash.as_deref(), cfg.token_dim)?;
        let count = self.scenes.map_or(scenes.len(), |n| (n as usize).min(scenes.len()));
        std::fs::create_dir_all(out).map_err(|e| format!("creating {}: {e}", out.display()))?;
        let spec = velox_models::velox::generator::GenerateSpec {
            steps: self.steps as usize,
            sampler: self.sampler.into(),
            guidance: self.guidance,
            seed: self.seed,
            precision: velox_engine::Precision::F32,
        };
        Ok(GeneratorEval { models, scenes, count, spec })
    }
}

#[derive(clap::Args)]
pub struct ClothEvalArgs {
    #[command(flatten)]
    common: GeneratorEvalArgs,
    /// Output folder: cloth.json and three plots per scene.
    #[arg(long, default_value = "velox-eval-cloth")]
    out: PathBuf,
    /// Surface points sampled per frame for its centre of mass, and the sampler's steps.
    #[arg(long, default_value_t = 2048, value_parser = clap::value_parser!(u64).range(1..=10_000_000))]
    points: u64,
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=1000))]
    sample_steps: u64,
}

#[derive(clap::Args)]
pub struct GenerationEvalArgs {
    #[command(flatten)]
    common: GeneratorEvalArgs,
    /// Where the Gaussian decoder's voxels come from for both token sets [default: predicted
    /// with --voxel-decoder, else surface]. `input` (the scene cloud's voxels) hands both the
    /// true shape, so it measures colour alone.
    #[arg(long, value_enum)]
    voxels: Option<VoxelArg>,
    /// A voxel decoder trained on the autoencoder's tokens, for `--voxels predicted`.
    #[arg(long)]
    voxel_decoder: Option<PathBuf>,
    /// Output folder: generation.json and a sheet per scene.
    #[arg(long, default_value = "velox-eval-generation")]
    out: PathBuf,
    /// Evaluate every Nth frame (0, N, 2N, ...).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u64).range(1..=24))]
    frame_step: u64,
    /// Novel views: the first N supervision cameras of each scene.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u64).range(1..=64))]
    views: u64,
    /// Surface points per frame sampled for `--voxels surface` (20 Heun steps).
    #[arg(long, default_value_t = 4096, value_parser = clap::value_parser!(u64).range(1..=100_000_000))]
    points: u64,
}

/// What every evaluation of a model on stored tokens takes.
#[derive(clap::Args)]
pub struct TokenEvalArgs {
    /// Dataset folder of held-out scenes (for the tracker, made with --tracks N: their video
    /// tracks are the queries and the truth).
    #[arg(long)]
    data: PathBuf,
    /// The model's checkpoint (`velox train voxels` or `velox train tracker`).
    #[arg(long)]
    checkpoint: PathBuf,
    /// The scenes' stored tokens [default: DATA/tokens; the tracker's, DATA/tokens-video].
    #[arg(long)]
    tokens: Option<PathBuf>,
    /// The autoencoder checkpoint the tokens must come from (else the one they record is
    /// checked, if it is still there).
    #[arg(long)]
    autoencoder: Option<PathBuf>,
    /// Write the metrics as JSON here [default: OUT/voxels.json or OUT/tracking.json].
    #[arg(long)]
    json: Option<PathBuf>,
    /// Evaluate only the first N scenes (in name order).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    scenes: Option<u64>,
}

#[derive(clap::Args)]
pub struct TrackingEvalArgs {
    #[command(flatten)]
    common: TokenEvalArgs,
    /// Output folder for the overlay images and tracking.json.
    #[arg(long, default_value = "velox-eval-tracking")]
    out: PathBuf,
    /// Scenes drawn: frames 0, 8, 16 and 23 of the video with the predicted tracks (top) and
    /// the true ones (bottom).
    #[arg(long, default_value_t = 2)]
    images: usize,
    /// How predictions are rescaled before the thresholds, as TAPVid-3D's evaluation does it:
    /// none, median (the benchmark's default), mean, per_trajectory, local_neighborhood,
    /// reproduce_2d, median_on_queries. The static baseline and the truth take the same.
    #[arg(long, default_value = "median", value_parser = parse_scaling)]
    scaling: velox_models::eval::tracking::Scaling,
}

fn parse_scaling(s: &str) -> Result<velox_models::eval::tracking::Scaling, String> {
    velox_models::eval::tracking::Scaling::parse(s).map_err(|e| e.to_string())
}

#[derive(clap::Args)]
pub struct VoxelEvalArgs {
    #[command(flatten)]
    common: TokenEvalArgs,
    /// Output folder for the projection images and voxels.json.
    #[arg(long, default_value = "velox-eval-voxels")]
    out: PathBuf,
    /// Evaluate every Nth frame (0, N, 2N, ...).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u64).range(1..=24))]
    frame_step: u64,
    /// Frames per scene drawn as projections along x, y and z (green: predicted and true,
    /// red: missed, blue: predicted wrongly).
    #[arg(long, default_value_t = 2)]
    images: usize,
    /// A voxel's probability above which it is occupied [default: the checkpoint's].
    #[arg(long, value_parser = probability)]
    threshold: Option<f32>,
    /// A cell's probability above which the fine stage refines it [default: the checkpoint's].
    #[arg(long, value_parser = probability)]
    cell_threshold: Option<f32>,
}

/// A probability strictly between 0 and 1.
fn probability(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(p) if p > 0.0 && p < 1.0 => Ok(p),
        _ => Err(format!("{s:?} is not a probability strictly between 0 and 1")),
    }
}

#[derive(clap::Args)]
pub struct ReconArgs {
    /// Dataset folder (scenes as `velox data` writes them); every scene is held out.
    #[arg(long)]
    data: PathBuf,
    /// Autoencoder checkpoint.
    #[arg(long)]
    checkpoint: PathBuf,
    /// Output folder for the side-by-side images (and eval.json unless --json says otherwise).
    #[arg(long, default_value = "velox-eval")]
    out: PathBuf,
    /// Write the metrics as JSON here (default OUT/eval.json).
    #[arg(long)]
    json: Option<PathBuf>,
    /// Evaluate only the first N scenes (in name order).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    scenes: Option<u64>,
    /// Supervision views per frame (the first V; default all of a scene's views).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    views: Option<u64>,
    /// Evaluate every Nth frame (0, N, 2N, ...).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u64).range(1..=24))]
    frame_step: u64,
    /// Points on each side of the Chamfer distance.
    #[arg(long, default_value_t = 8000, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
    points: u64,
    /// Where the Gaussian decoder's voxels come from, comma-separated; each is measured, side
    /// by side [default: predicted,input with --voxel-decoder, else input].
    #[arg(long, value_enum, value_delimiter = ',')]
    voxels: Vec<VoxelArg>,
    /// A voxel decoder (`velox train voxels`) trained on this autoencoder's tokens, for
    /// `--voxels predicted`.
    #[arg(long)]
    voxel_decoder: Option<PathBuf>,
    /// Side-by-side images (ground truth | ours) saved per scene.
    #[arg(long, default_value_t = 4)]
    images: usize,
    /// Seed of the encoder's queries and the sampler's noise.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Integration steps of the surface sampler (the Chamfer samples).
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u64).range(1..=10_000))]
    steps: u64,
    /// The surface sampler.
    #[arg(long, value_enum, default_value_t = SamplerArg::Heun)]
    sampler: SamplerArg,
    /// Precision of the networks: f32, or f16 (matrix products and attention on f16 operands
    /// with f32 accumulation).
    #[arg(long, value_enum, default_value_t = PrecisionArg::F32)]
    precision: PrecisionArg,
}

/// What `eval.json` holds: the inputs and the report.
#[derive(Serialize)]
struct EvalJson<'a> {
    checkpoint: String,
    data: String,
    #[serde(flatten)]
    report: &'a ReconReport,
}

/// The progress bar over frames, and the side-by-side images written under `--out`.
struct Images<'a> {
    out: &'a std::path::Path,
    bar: ProgressBar,
}

impl ReconObserver for Images<'_> {
    fn scene(&mut self, name: &str) {
        self.bar.set_message(name.to_string());
    }

    fn frame(&mut self) {
        self.bar.inc(1);
    }

    fn image(
        &mut self,
        scene: &str,
        frame: usize,
        view: usize,
        rgb: &[f32],
        width: usize,
        height: usize,
    ) -> velox_engine::Result<Option<String>> {
        let dir = self.out.join(scene);
        std::fs::create_dir_all(&dir)
            .map_err(|e| velox_engine::Error::Io(format!("cannot create {}: {e}", dir.display())))?;
        let name = format!("f{frame:02}_v{view:02}.png");
        write_png(&dir.join(&name), rgb, 2 * width as u32, height as u32)?;
        Ok(Some(format!("{scene}/{name}")))
    }
}

pub fn run(cmd: EvalCommand) -> CliResult<()> {
    match cmd {
        EvalCommand::Recon(a) => run_recon(&a),
        EvalCommand::Voxels(a) => run_voxels(&a),
        EvalCommand::Tracking(a) => run_tracking(&a),
        EvalCommand::Generation(a) => run_generation(&a),
        EvalCommand::Cloth(a) => run_cloth(&a),
        EvalCommand::Tapvid3d(a) => run_tapvid3d(&a),
    }
}

fn run_tapvid3d(a: &Tapvid3dArgs) -> CliResult<()> {
    use velox_models::eval::tracking::Scaling;
    let scalings = a.scaling.iter().map(|s| Scaling::parse(s)).collect::<velox_engine::Result<Vec<_>>>()?;
    let mut clips = Vec::new();
    for p in &a.ground_truth {
        if p.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(p)
                .map_err(|e| format!("cannot read {}: {e}", p.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| f.extension().is_some_and(|x| x == "npz"))
                .collect();
            if found.is_empty() {
                return Err(format!("{} holds no .npz clip", p.display()).into());
            }
            found.sort();
            clips.extend(found);
        } else {
            clips.push(p.clone());
        }
    }
    let predictions: Vec<PathBuf> = if a.predictions.is_dir() {
        clips.iter().map(|c| a.predictions.join(c.file_name().unwrap_or_default())).collect()
    } else if clips.len() == 1 {
        vec![a.predictions.clone()]
    } else {
        return Err(format!(
            "--predictions {} is a file, and {} clips are scored: give the folder of their predictions",
            a.predictions.display(),
            clips.len()
        )
        .into());
    };
    let names: Vec<&str> = scalings.iter().map(|s| s.name()).collect();
    println!("{:<40} {:<18} {:>8} {:>8} {:>8}", "clip", "scaling", "AJ", "APD", "OA");
    let mut rows = Vec::new();
    let gt: Vec<&Path> = clips.iter().map(PathBuf::as_path).collect();
    let pred: Vec<&Path> = predictions.iter().map(PathBuf::as_path).collect();
    let means = velox_tasks::tapvid3d::evaluate(&gt, &pred, &scalings, &mut |clip, metrics| {
        let name = clip.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        for (s, m) in names.iter().zip(metrics) {
            println!(
                "{name:<40} {s:<18} {:>8.4} {:>8.4} {:>8.4}",
                m.average_jaccard, m.apd_visible, m.occlusion_accuracy
            );
        }
        rows.push(serde_json::json!({ "clip": clip.display().to_string(), "metrics": names.iter().zip(metrics).map(|(s, m)| (s.to_string(), m)).collect::<std::collections::BTreeMap<_, _>>() }));
    })?;
    for (s, m) in names.iter().zip(&means) {
        println!(
            "{:<40} {s:<18} {:>8.4} {:>8.4} {:>8.4}",
            format!("mean of {} clip(s)", clips.len()),
            m.average_jaccard,
            m.apd_visible,
            m.occlusion_accuracy
        );
    }
    if let Some(out) = &a.out {
        let mean: std::collections::BTreeMap<String, _> =
            names.iter().map(|s| s.to_string()).zip(&means).collect();
        let json = serde_json::json!({ "clips": rows, "mean": mean });
        write_bytes(out, serde_json::to_string_pretty(&json)?.as_bytes())?;
        println!("wrote {}", out.display());
    }
    Ok(())
}

fn run_tracking(a: &TrackingEvalArgs) -> CliResult<()> {
    use velox_models::eval::tracking::{TrackingMetrics, METRIC_RESOLUTION};
    let c = &a.common;
    let gpu = Gpu::new()?;
    let scenes = TrackScenes::open(&gpu, &c.data, c.tokens.as_deref(), c.autoencoder.as_deref())?;
    if let Some(note) = scenes.0.checkpoint().note() {
        eprintln!("note: {note}");
    }
    let tracker = Tracker::load(&gpu, &c.checkpoint)?;
    scenes.0.check_model("tracker", tracker.cfg.encoder_hash.as_deref(), tracker.cfg.token_dim)?;
    std::fs::create_dir_all(&a.out).map_err(|e| format!("creating {}: {e}", a.out.display()))?;
    let json = c.json.clone().unwrap_or_else(|| a.out.join("tracking.json"));
    let count = c.scenes.map_or(scenes.len(), |n| (n as usize).min(scenes.len()));
    println!(
        "evaluating the {} tracker ({}) on {count} scenes of {} on {}; predictions rescaled by {}, \
         thresholds in pixels of a {METRIC_RESOLUTION}-pixel short side",
        tracker.cfg.name,
        c.checkpoint.display(),
        c.data.display(),
        gpu.caps().name,
        a.scaling.name()
    );
    let mut overlays =
        Overlays { out: &a.out, first: a.images, bar: progress(count, "scenes"), images: Vec::new() };
    let evaluation = velox_tasks::evaluate::tracking(&tracker, &scenes, count, a.scaling, &mut overlays)?;
    overlays.bar.finish_and_clear();
    let (images, unseen, reports, mean) =
        (overlays.images, evaluation.left_out, evaluation.scenes, evaluation.mean);
    if !unseen.is_empty() {
        eprintln!(
            "note: {} scene(s) whose video shows none of their tracks are left out of the means: {}",
            unseen.len(),
            unseen.join(", ")
        );
    }
    println!(
        "{:<24} {:<16} {:>7} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "scene", "method", "queries", "L2 all", "L2 vis", "APD all", "APD vis", "AJ", "OA"
    );
    let row = |name: &str, method: &str, queries: usize, m: &TrackingMetrics| {
        println!(
            "{name:<24} {method:<16} {queries:>7} {:>8.4} {:>8.4} {:>8.4} {:>8.4} {:>8.4} {:>8.4}",
            m.l2_all, m.l2_visible, m.apd_all, m.apd_visible, m.average_jaccard, m.occlusion_accuracy
        )
    };
    for r in reports.iter().chain(std::iter::once(&mean)) {
        row(&r.name, "tracker", r.queries, &r.tracker);
        row("", "static", r.queries, &r.static_baseline);
        if r.name == "mean" {
            row("", "truth", r.queries, &r.truth);
        }
    }
    println!(
        "TAPVid-3D's metrics as its evaluation computes them, in the video camera's frame: predictions \
         rescaled by {} (--scaling), thresholds of 1 to 16 pixels of a {METRIC_RESOLUTION}-pixel short side \
         at the true depth (APD vis and AJ are the benchmark's APD and AJ; L2 and APD all are not its); \
         means over scenes; occlusion is the video's depth test for every method (the tracker learns \
         none); static: every query stays on its first frame; truth: the true tracks (the ceiling)",
        a.scaling.name()
    );
    let file = serde_json::json!({
        "checkpoint": c.checkpoint.display().to_string(),
        "data": c.data.display().to_string(),
        "scaling": a.scaling.name(),
        "threshold_resolution": METRIC_RESOLUTION,
        "left_out": unseen,
        "mean": mean,
        "scenes": reports,
        "images": images,
    });
    write_bytes(&json, serde_json::to_string_pretty(&file)?.as_bytes())?;
    println!("wrote {} and {} overlay image(s) under {}", json.display(), images.len(), a.out.display());
    Ok(())
}

/// The progress bar over scenes, and the overlays of the first scenes written under `--out`.
struct Overlays<'a> {
    out: &'a std::path::Path,
    first: usize,
    bar: ProgressBar,
    images: Vec<String>,
}

impl velox_tasks::evaluate::TrackingObserver for Overlays<'_> {
    fn scene(&mut self, name: &str) {
        self.bar.set_message(name.to_string());
    }

    fn measured(
        &mut self,
        index: usize,
        name: &str,
        video: &velox_data::rgbd::RgbdVideo,
        scene: &velox_models::eval::tracking::TrackingScene,
        predicted: &[velox_models::velox::tracker::Track],
    ) -> velox_engine::Result<()> {
        if index < self.first {
            let path = self.out.join(format!("{name}.png"));
            write_overlays(&path, video, scene, predicted)?;
            self.images.push(path.display().to_string());
        }
        Ok(())
    }

    fn done(&mut self) {
        self.bar.inc(1);
    }
}

/// Frames 0, 8, 16 and 23 of the video with the predicted tracks over them (top row) and the
/// true ones (bottom row), occluded stretches faded; enlarged (each pixel a k x k block) to at
/// least 128 px a frame.
fn write_overlays(
    path: &std::path::Path,
    video: &velox_data::rgbd::RgbdVideo,
    scene: &velox_models::eval::tracking::TrackingScene,
    predicted: &[velox_models::velox::tracker::Track],
) -> velox_engine::Result<()> {
    use crate::overlay::{colours, draw_tracks, side_by_side};
    let cam = &video.camera;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let hidden_of = |tracks: &[velox_models::velox::tracker::Track]| -> Vec<[bool; 24]> {
        let (_, hidden) = scene.in_camera(tracks);
        hidden.chunks_exact(24).map(|c| std::array::from_fn(|f| c[f])).collect()
    };
    let truth_hidden: Vec<[bool; 24]> = scene.visible.iter().map(|v| v.map(|s| !s)).collect();
    let colour = colours(scene.truth, cam);
    let mut rows = Vec::new();
    for (tracks, hidden) in [(predicted, hidden_of(predicted)), (scene.truth, truth_hidden)] {
        let frames: Vec<Vec<f32>> = [0, 8, 16, 23]
            .iter()
            .map(|&f| {
                let mut rgb = video.rgb[f].clone();
                draw_tracks(&mut rgb, cam, tracks, &hidden, &colour, f);
                rgb
            })
            .collect();
        rows.extend(side_by_side(&frames, w, h));
    }
    // Small videos are drawn at their own pixels, then shown at least 128 px a frame.
    let k = 128usize.div_ceil(w.min(h)).max(1);
    let sheet = crate::overlay::enlarged(&rows, 4 * w, 2 * h, k);
    write_png(path, &sheet, (4 * w * k) as u32, (2 * h * k) as u32)?;
    Ok(())
}

/// The progress bar over scenes, and the projections of each scene's first frames.
struct Projections<'a> {
    out: &'a std::path::Path,
    per_scene: usize,
    bar: ProgressBar,
    images: Vec<String>,
}

impl velox_tasks::evaluate::VoxelObserver for Projections<'_> {
    fn scene(&mut self, name: &str) {
        self.bar.set_message(name.to_string());
    }

    fn measured(
        &mut self,
        r: &velox_models::eval::voxels::SceneVoxels,
        occupancy: &[u64],
    ) -> velox_engine::Result<()> {
        let n = r.frames.len();
        for k in 0..self.per_scene.min(n) {
            let f = &r.frames[k * n / self.per_scene.min(n)];
            let truth = &occupancy[f.frame * FRAME_WORDS..(f.frame + 1) * FRAME_WORDS];
            let dir = self.out.join(&r.name);
            std::fs::create_dir_all(&dir)
                .map_err(|e| velox_engine::Error::Io(format!("creating {}: {e}", dir.display())))?;
            let path = dir.join(format!("f{:02}_xyz.png", f.frame));
            write_png(&path, &projections(&f.predicted, truth), 192, 64)?;
            self.images.push(path.display().to_string());
        }
        self.bar.inc(1);
        Ok(())
    }
}

fn run_voxels(a: &VoxelEvalArgs) -> CliResult<()> {
    let c = &a.common;
    let gpu = Gpu::new()?;
    let scenes = TokenScenes::open(&gpu, &c.data, c.tokens.as_deref(), c.autoencoder.as_deref())?;
    if let Some(note) = scenes.checkpoint().note() {
        eprintln!("note: {note}");
    }
    let mut decoder = VoxelDecoder::load(&gpu, &c.checkpoint)?;
    scenes.check_model("voxel decoder", decoder.cfg.encoder_hash.as_deref(), decoder.cfg.token_dim)?;
    decoder.cfg.threshold = a.threshold.unwrap_or(decoder.cfg.threshold);
    decoder.cfg.cell_threshold = a.cell_threshold.unwrap_or(decoder.cfg.cell_threshold);
    std::fs::create_dir_all(&a.out).map_err(|e| format!("creating {}: {e}", a.out.display()))?;
    let json = c.json.clone().unwrap_or_else(|| a.out.join("voxels.json"));
    let count = c.scenes.map_or(scenes.len(), |n| (n as usize).min(scenes.len()));
    println!(
        "evaluating the {} voxel decoder ({}; cells above {}, voxels above {}) on {count} scenes of {} on {}",
        decoder.cfg.name,
        c.checkpoint.display(),
        decoder.cfg.cell_threshold,
        decoder.cfg.threshold,
        c.data.display(),
        gpu.caps().name
    );
    let mut drawn =
        Projections { out: &a.out, per_scene: a.images, bar: progress(count, "scenes"), images: Vec::new() };
    let evaluation =
        velox_tasks::evaluate::voxels(&decoder, &scenes, count, a.frame_step as usize, &mut drawn)?;
    drawn.bar.finish_and_clear();
    let (images, reports, mean) = (drawn.images, evaluation.scenes, evaluation.mean);
    println!(
        "{:<24} {:>7} {:>9} {:>9} {:>7} {:>7} {:>9} {:>9} {:>8} {:>11}",
        "scene",
        "frames",
        "accuracy",
        "precision",
        "recall",
        "IoU",
        "true",
        "predicted",
        "cells",
        "cell recall"
    );
    let row = |name: &str, frames: String, m: &VoxelMetrics| {
        println!(
            "{name:<24} {frames:>7} {:>9.5} {:>9.4} {:>7.4} {:>7.4} {:>9.0} {:>9.0} {:>8.0} {:>11.4}",
            m.accuracy,
            m.precision,
            m.recall,
            m.iou,
            m.true_voxels,
            m.predicted_voxels,
            m.refined_cells,
            m.cell_recall
        )
    };
    for r in &reports {
        row(&r.name, r.frames.len().to_string(), &r.mean);
    }
    row("mean", String::new(), &mean);
    println!(
        "means over frames and scenes; true and predicted count occupied voxels of the 64^3 grid, \
         cells the coarse cells the fine stage refined, cell recall the share of the true cells \
         among them; accuracy alone says little (an empty prediction scores about 99 %)"
    );
    let file = serde_json::json!({
        "checkpoint": c.checkpoint.display().to_string(),
        "data": c.data.display().to_string(),
        "frame_step": a.frame_step,
        "threshold": decoder.cfg.threshold,
        "cell_threshold": decoder.cfg.cell_threshold,
        "mean": mean,
        "scenes": reports,
        "images": images,
    });
    write_bytes(&json, serde_json::to_string_pretty(&file)?.as_bytes())?;
    println!("wrote {} and the projections under {}", json.display(), a.out.display());
    Ok(())
}

fn run_recon(a: &ReconArgs) -> CliResult<()> {
    let gpu = Gpu::new()?;
    let mut scenes = SceneFolders::open(&gpu, &a.data)?;
    if let Some(n) = a.scenes {
        scenes.truncate(n as usize);
    }
    let mut ae = Autoencoder::load(&gpu, &a.checkpoint)?;
    ae.set_precision(a.precision.into())?;
    let sources: Vec<VoxelSource> = match (a.voxels.is_empty(), a.voxel_decoder.is_some()) {
        (false, _) => a.voxels.iter().map(|&v| v.into()).collect(),
        (true, true) => vec![VoxelSource::Predicted, VoxelSource::Input],
        (true, false) => vec![VoxelSource::Input],
    };
    let decoder = voxel_decoder(&gpu, a.voxel_decoder.as_deref(), &a.checkpoint, &sources)?;
    std::fs::create_dir_all(&a.out).map_err(|e| format!("creating {}: {e}", a.out.display()))?;
    let json = a.json.clone().unwrap_or_else(|| a.out.join("eval.json"));
    let count = scenes.dirs().len();
    println!(
        "evaluating the {} autoencoder ({}, {}) on {count} scenes of {} on {}",
        ae.cfg.name,
        ae.precision().name(),
        a.checkpoint.display(),
        a.data.display(),
        gpu.caps().name
    );
    let options = ReconOptions {
        views: a.views.map(|v| v as usize),
        frame_step: a.frame_step as usize,
        sampling: Sampling { points: a.points as usize, steps: a.steps as usize, sampler: a.sampler.into() },
        voxels: sources,
        images: a.images,
        seed: a.seed,
    };
    recon(&ae, decoder.as_ref(), &scenes, &options, &a.out, &json, &a.checkpoint, &a.data)?;
    Ok(())
}

/// Evaluates `ae` on `scenes` with a progress bar, writes the side-by-side images under `out`
/// and the report to `json` (with the checkpoint and data paths it names), and prints the
/// table: `velox eval recon` after its arguments are read, and the demo's last step.
#[allow(clippy::too_many_arguments)]
pub fn recon(
    ae: &Autoencoder,
    decoder: Option<&VoxelDecoder>,
    scenes: &SceneFolders,
    options: &ReconOptions,
    out: &Path,
    json: &Path,
    checkpoint: &Path,
    data: &Path,
) -> CliResult<ReconReport> {
    let bar = progress(scenes.dirs().len() * frames(options.frame_step).len(), "frames");
    let mut images = Images { out, bar };
    let report = evaluate(ae, decoder, scenes, options, &mut images)?;
    images.bar.finish_and_clear();
    print_table(&report);
    let file = EvalJson {
        checkpoint: checkpoint.display().to_string(),
        data: data.display().to_string(),
        report: &report,
    };
    write_bytes(json, serde_json::to_string_pretty(&file)?.as_bytes())?;
    println!(
        "wrote {} and the side-by-side images (ground truth | ours) under {}",
        json.display(),
        out.display()
    );
    Ok(report)
}

fn print_table(r: &ReconReport) {
    println!(
        "{:<24} {:>7} {:>9} {:>7} {:>13} {:>13}",
        "scene", "frames", "PSNR dB", "SSIM", "Chamfer", "GT halves"
    );
    for s in &r.scenes {
        println!(
            "{:<24} {:>7} {:>9.2} {:>7.4} {:>13.4e} {:>13.4e}",
            s.name,
            s.frames.len(),
            s.psnr,
            s.ssim,
            s.chamfer,
            s.chamfer_gt_halves
        );
    }
    let m = &r.mean;
    println!(
        "{:<24} {:>7} {:>9.2} {:>7.4} {:>13.4e} {:>13.4e}",
        "mean", "", m.psnr, m.ssim, m.chamfer, m.chamfer_gt_halves
    );
    if m.sources.len() > 1 {
        println!("PSNR and SSIM by the source of the Gaussian decoder's voxels (scene means):");
        print!("{:<24}", "scene");
        for src in &m.sources {
            print!(" {:>11} {:>7}", format!("{} dB", format!("{:?}", src.source).to_lowercase()), "SSIM");
        }
        println!();
        let rows = r.scenes.iter().map(|s| (s.name.as_str(), &s.sources)).chain([("mean", &m.sources)]);
        for (name, sources) in rows {
            print!("{name:<24}");
            for src in sources {
                print!(" {:>11.2} {:>7.4}", src.psnr, src.ssim);
            }
            println!();
        }
    }
    println!(
        "GT halves: the Chamfer distance between the ground truth's even and odd points, what \
         two samples of the true surface score at this density: a sparse cloud cannot show a \
         small Chamfer distance"
    );
    println!(
        "paper (Objaverse, 256 scenes, 532 px): PSNR 35.11, SSIM 0.983, Chamfer 36.36e-5; \
         voxels from the {}, Chamfer over {} points",
        match r.voxels[0] {
            VoxelSource::Input => "input cloud (as in training)",
            VoxelSource::Surface => "decoded surface samples",
            VoxelSource::Predicted => "voxel decoder's prediction",
        },
        r.chamfer_points
    );
}

/// The progress bar over scenes, and a sheet per scene: per kept frame a column; rows truth,
/// generated, encoded for the input view and the first novel view.
struct Sheets<'a> {
    out: &'a std::path::Path,
    bar: ProgressBar,
    columns: Vec<Vec<Vec<f32>>>,
}

impl velox_tasks::evaluate::GenerationObserver for Sheets<'_> {
    fn scene(&mut self, name: &str) {
        self.bar.set_message(name.to_string());
        self.columns.clear();
    }

    fn renders(
        &mut self,
        _name: &str,
        _views: &velox_models::eval::generation::GenerationViews,
        frame: velox_models::eval::generation::FrameRenders,
    ) -> velox_engine::Result<()> {
        self.columns.push(frame.views.into_iter().take(2).flatten().collect());
        Ok(())
    }

    fn done(
        &mut self,
        name: &str,
        views: &velox_models::eval::generation::GenerationViews,
    ) -> velox_engine::Result<()> {
        let columns = std::mem::take(&mut self.columns);
        let (w, h) = (views.input.width as usize, views.input.height as usize);
        let same_size = views.novel.iter().all(|c| (c.width as usize, c.height as usize) == (w, h));
        if same_size && !columns.is_empty() {
            let rows = columns[0].len();
            let images: Vec<Vec<f32>> =
                (0..rows).flat_map(|r| columns.iter().map(move |c| c[r].clone())).collect();
            let cols = columns.len();
            let k = (128 / w.max(1)).clamp(1, 4);
            let sheet =
                crate::overlay::enlarged(&crate::generate::grid(&images, cols, w, h), cols * w, rows * h, k);
            write_png(
                &self.out.join(format!("{name}.png")),
                &sheet,
                (cols * w * k) as u32,
                (rows * h * k) as u32,
            )?;
        }
        self.bar.inc(1);
        Ok(())
    }
}

fn run_generation(a: &GenerationEvalArgs) -> CliResult<()> {
    use velox_models::eval::generation::{GenerationMean, GenerationScene};
    use velox_tasks::evaluate::GenerationOptions;

    let c = &a.common;
    let gpu = Gpu::new()?;
    let eval = c.open(&gpu, &a.out)?;
    let (m, scenes, count) = (&eval.models, &eval.scenes, eval.count);
    let cfg = &m.generator.cfg;
    let default_voxels = if a.voxel_decoder.is_some() { VoxelArg::Predicted } else { VoxelArg::Surface };
    let source = VoxelSource::from(a.voxels.unwrap_or(default_voxels));
    let decoder = voxel_decoder(&gpu, a.voxel_decoder.as_deref(), &c.autoencoder, &[source])?;
    if source == VoxelSource::Input {
        eprintln!(
            "note: --voxels input decodes both token sets over the scene's true voxels: the shape is given"
        );
    }
    let frames = frames(a.frame_step as usize);
    let sheet_at = crate::generate::sheet_frames(&frames);
    let sampling = Sampling { points: a.points as usize, steps: 20, sampler: SamplerArg::Heun.into() };
    println!(
        "evaluating the {} generator on {count} scene(s) of {}: {} frames, the input view and {} novel views, \
         voxels {source:?}, {} {:?} steps, guidance {}",
        cfg.name,
        c.data.display(),
        frames.len(),
        a.views,
        c.steps,
        c.sampler,
        c.guidance
    );
    let options = GenerationOptions {
        spec: eval.spec,
        source,
        voxel_decoder: decoder.as_ref(),
        sampling,
        frames: frames.clone(),
        views: a.views as usize,
        kept: sheet_at,
    };
    let mut sheets = Sheets { out: &a.out, bar: progress(count, "scenes"), columns: Vec::new() };
    let results = velox_tasks::evaluate::generation(&gpu, m, scenes, count, &options, &mut sheets)?;
    sheets.bar.finish_and_clear();
    let mean = GenerationMean::of(&results);
    println!(
        "{:<20} {:>22} {:>24} {:>11}",
        "", "input view PSNR / SSIM", "novel views PSNR / SSIM", "token NMSE"
    );
    let row = |label: &str, s: &velox_models::eval::generation::ViewScores, nmse: Option<f64>| {
        let nmse = nmse.map_or(String::new(), |v| format!("{v:>11.4}"));
        println!(
            "{label:<20} {:>14.2} / {:.4} {:>16.2} / {:.4} {nmse}",
            s.input.psnr, s.input.ssim, s.novel.psnr, s.novel.ssim
        );
    };
    for r in &results {
        row(&format!("{} gen", r.scene), &r.generated, Some(r.token_nmse));
        row(&format!("{} enc", r.scene), &r.encoded, None);
    }
    row("mean generated", &mean.generated, Some(mean.token_nmse));
    row("mean encoded", &mean.encoded, None);
    #[derive(Serialize)]
    struct Report<'a> {
        generator: String,
        autoencoder: String,
        voxels: VoxelSource,
        steps: u64,
        sampler: SamplerArg,
        guidance: f32,
        seed: u64,
        frames: Vec<usize>,
        novel_views: u64,
        mean: GenerationMean,
        scenes: &'a [GenerationScene],
    }
    let report = Report {
        generator: c.checkpoint.display().to_string(),
        autoencoder: c.autoencoder.display().to_string(),
        voxels: source,
        steps: c.steps,
        sampler: c.sampler,
        guidance: c.guidance,
        seed: c.seed,
        frames,
        novel_views: a.views,
        mean,
        scenes: &results,
    };
    write_bytes(&a.out.join("generation.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    println!(
        "wrote {} and a sheet per scene (columns: frames; rows: truth, generated, encoded, for the input view \
         and the first novel view)",
        a.out.join("generation.json").display()
    );
    Ok(())
}

/// The progress bar over decoded frames, and each scene's decoded surfaces (generated, then
/// encoded; a list of frames each) for its clip.
struct Frames {
    bar: ProgressBar,
    surfaces: Vec<(String, [Vec<Vec<f32>>; 2])>,
}

impl velox_tasks::evaluate::ClothObserver for Frames {
    fn scene(&mut self, name: &str) {
        self.bar.set_message(name.to_string());
        self.surfaces.push((name.to_string(), Default::default()));
    }

    fn frame(&mut self, tokens: ClothTokens, _frame: usize, points: &[f32]) {
        if let Some((_, s)) = self.surfaces.last_mut() {
            s[(tokens == ClothTokens::Encoded) as usize].push(points.to_vec());
        }
        self.bar.inc(1);
    }
}

fn run_cloth(a: &ClothEvalArgs) -> CliResult<()> {
    use velox_models::eval::cloth::ClothScene;

    let c = &a.common;
    let gpu = Gpu::new()?;
    let eval = c.open(&gpu, &a.out)?;
    let (m, scenes, count) = (&eval.models, &eval.scenes, eval.count);
    let cfg = &m.generator.cfg;
    let sampling = Sampling {
        points: a.points as usize,
        steps: a.sample_steps as usize,
        sampler: SamplerArg::Heun.into(),
    };
    println!(
        "evaluating the {} generator ({:?} task) on {count} cloth scene(s) of {}: the centre of mass of {} surface \
         points a frame",
        cfg.name,
        cfg.task,
        c.data.display(),
        a.points
    );
    let frames = velox_models::velox::autoencoder::FRAMES;
    let bar = progress(count * 2 * frames, "frames decoded (generated, then encoded)");
    let mut observer = Frames { bar, surfaces: Vec::new() };
    let evaluated =
        velox_tasks::evaluate::cloth(&gpu, m, scenes, count, &eval.spec, &sampling, &mut observer)?;
    observer.bar.finish_and_clear();
    let mut results: Vec<ClothScene> = Vec::with_capacity(evaluated.len());
    let mut dt = 0.01;
    for (i, r) in evaluated.into_iter().enumerate() {
        dt = r.frame_seconds;
        let name = &r.scene.scene;
        r.scene.plot(&a.out.join(name), dt)?;
        if let Some((_, surfaces)) = observer.surfaces.iter().find(|(n, _)| n == name) {
            // The scene beside the surface decoded from the generated and the encoded tokens.
            let [generated, encoded] = surfaces;
            // Surface points are light grey on black, whatever the scene's background.
            let splat = |f: usize, camera: &velox_engine::ops::raster::Camera, _background| {
                Ok(vec![splat_points(&gpu, &generated[f], camera)?, splat_points(&gpu, &encoded[f], camera)?])
            };
            let frames: Vec<usize> = (0..generated.len()).collect();
            clip_gif(&scenes.dirs()[i], &frames, splat, &a.out.join(format!("{name}.gif")), 100, None)?;
        }
        results.push(r.scene);
    }
    println!("{:<20} {:>28} {:>26}", "", "RMSE along gravity, generated", "encoded (the ceiling)");
    for r in &results {
        println!("{:<20} {:>28.4} {:>26.4}", r.scene, r.rmse_generated, r.rmse_encoded);
    }
    let mean =
        |f: &dyn Fn(&ClothScene) -> f64| results.iter().map(f).sum::<f64>() / results.len().max(1) as f64;
    let (gen, enc) = (mean(&|r| r.rmse_generated), mean(&|r| r.rmse_encoded));
    println!("{:<20} {gen:>28.4} {enc:>26.4}", "mean");
    let cm = velox_models::eval::cloth::CM_PER_UNIT;
    println!(
        "scene units (half metres); the generated mean is {:.2} cm, the paper's unit (it reports 1 cm)",
        gen * cm
    );
    #[derive(Serialize)]
    struct Report<'a> {
        generator: String,
        autoencoder: String,
        points: u64,
        sample_steps: u64,
        steps: u64,
        guidance: f32,
        seed: u64,
        frame_seconds: f64,
        mean_rmse_generated: f64,
        mean_rmse_encoded: f64,
        mean_rmse_generated_cm: f64,
        scenes: &'a [ClothScene],
    }
    let report = Report {
        generator: c.checkpoint.display().to_string(),
        autoencoder: c.autoencoder.display().to_string(),
        points: a.points,
        sample_steps: a.sample_steps,
        steps: c.steps,
        guidance: c.guidance,
        seed: c.seed,
        frame_seconds: dt,
        mean_rmse_generated: gen,
        mean_rmse_encoded: enc,
        mean_rmse_generated_cm: gen * cm,
        scenes: &results,
    };
    write_bytes(&a.out.join("cloth.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    println!(
        "wrote {} and SCENE_height.png, _velocity.png, _acceleration.png per scene (simulated, generated, encoded), \
         and SCENE.gif (the scene | generated | encoded)",
        a.out.join("cloth.json").display()
    );
    Ok(())
}
