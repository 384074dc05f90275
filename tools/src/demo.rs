//! `velox demo`: the whole pipeline on one scene, on whatever device is present: make a
//! procedural animated scene, train an autoencoder on it, decode its surface points and
//! Gaussians, render them beside the ground truth and measure them. Sizes follow the device:
//! under three minutes on two CPU cores with lavapipe (the CPU demo config below, 96 px), a
//! longer and larger run on a GPU.

use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use velox_data::format::write_scene;
use velox_data::{procedural, SynthOptions};
use velox_engine::ops::raster::Camera;
use velox_engine::Gpu;
use velox_io::cloud::CHANNELS;
use velox_io::write_bytes;
use velox_models::velox::autoencoder::FRAMES;
use velox_models::Model;

use velox_models::config::AutoencoderConfig;
use velox_models::eval::recon::ReconOptions;
use velox_models::train::collective::SingleProcess;
use velox_models::velox::autoencoder::Autoencoder;
use velox_models::velox::decode::{Decoding, FrameOutput, Sampling, VoxelSource};
use velox_tasks::SceneFolders;

use crate::decode::{progress, read_cloud, render_written, write_report, DecodeRecord};
use crate::eval::recon;
use crate::interrupt::Interrupt;
use crate::overlay::clip_gif;
use crate::train::{train_autoencoder, AutoencoderArgs, RunArgs};
use crate::CliResult;

#[derive(Args)]
pub struct DemoArgs {
    /// Folder for the demo's outputs (a previous demo's folder is replaced).
    #[arg(long, default_value = "velox-demo")]
    pub out: PathBuf,
    /// Model sizes: paper, small, tiny or a JSON file (default: the CPU demo config on a CPU
    /// device, written to OUT/config.json; small on a GPU).
    #[arg(long)]
    pub config: Option<String>,
    /// Training steps (default: 900 on a CPU device, 2000 on a GPU; the last quarter cools the
    /// learning rate down).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps: Option<u64>,
    /// Image side of the scene's views (default: 96 on a CPU device, 128 on a GPU).
    #[arg(long, value_parser = clap::value_parser!(u32).range(16..=2048))]
    pub res: Option<u32>,
    /// Points of the 4D cloud (default: 60000).
    #[arg(long, value_parser = clap::value_parser!(u64).range(64..))]
    pub points: Option<u64>,
    /// Seed of the scene and of the training run.
    #[arg(long, default_value_t = 11)]
    pub seed: u64,
}

/// The model a CPU device trains in the demo: the tiny config's networks (width 32) with the
/// small config's Gaussians (scales of 0.002 to 0.03 within 0.05 of their voxel's centre) on a
/// grid of 64, four to a voxel, so that a 96 px view is covered by Gaussians of about a pixel;
/// the encoder reads 8000 of the cloud's points a step, each step renders two views, and the
/// learning rate peaks at 0.01 after 20 steps. On two cores, 900 steps take two and a
/// half minutes to 25.2 dB on the demo's scene; fewer, larger Gaussians (the tiny config's
/// grid of 16) blur the object (20.9 dB), and the encoder reading all 60000 points triples a
/// step's time for 0.3 dB.
pub fn cpu_demo_config() -> AutoencoderConfig {
    let mut c = AutoencoderConfig::tiny();
    c.name = "cpu-demo".into();
    c.gaussians.grid = 64;
    c.gaussians.gaussians_per_voxel = 4;
    c.gaussians.scale_min = 0.002;
    c.gaussians.scale_max = 0.03;
    c.gaussians.offset_range = 0.05;
    c.encoder_points = 8000;
    c.views_per_step = 2;
    c.peak_lr = 0.01;
    c.warmup = 20;
    c
}

/// Marks a folder as a demo's, so that only a demo's folder is ever replaced.
const MARKER: &str = "demo.json";

fn prepare(out: &Path) -> CliResult<()> {
    if out.exists() {
        let empty = std::fs::read_dir(out).map(|mut d| d.next().is_none()).unwrap_or(false);
        if !empty && !out.join(MARKER).exists() {
            return Err(format!(
                "{} exists and is not a previous demo's folder; choose another --out",
                out.display()
            )
            .into());
        }
        for sub in ["data", "train", "decoded", "eval"] {
            let _ = std::fs::remove_dir_all(out.join(sub));
        }
    }
    std::fs::create_dir_all(out).map_err(|e| format!("creating {}: {e}", out.display()))?;
    write_bytes(&out.join(MARKER), b"{}")?;
    Ok(())
}

pub fn run(args: &DemoArgs) -> CliResult<()> {
    let started = Instant::now();
    let gpu = Gpu::new()?;
    let cpu = gpu.caps().kind == "CPU";
    let steps = args.steps.unwrap_or(if cpu { 900 } else { 2000 });
    let res = args.res.unwrap_or(if cpu { 96 } else { 128 });
    let points = args.points.unwrap_or(60_000) as usize;
    let out = &args.out;
    prepare(out)?;
    let config = match &args.config {
        Some(c) => c.clone(),
        None if cpu => {
            let path = out.join("config.json");
            write_bytes(&path, serde_json::to_string_pretty(&cpu_demo_config())?.as_bytes())?;
            path.display().to_string()
        }
        None => "small".into(),
    };
    println!(
        "velox demo on {} ({}): a {res}x{res} scene of {points} points, the {config} autoencoder, {steps} steps\n",
        gpu.caps().name,
        gpu.caps().kind
    );

    // 1. A procedural animated scene.
    println!("1/4 making the scene");
    let scene_dir = out.join("data").join("scene_00000");
    let (recipe, mesh) = procedural::scene(args.seed, None)?;
    let bar = ProgressBar::new(24);
    bar.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} frames  {elapsed}").expect("a valid template"),
    );
    let opts = SynthOptions { res, points, supersample: 2, tracks: 64, ..Default::default() };
    let source = format!("procedural seed {}: {recipe:?}", args.seed);
    write_scene(&gpu, &mesh, &source, None, args.seed, &opts, &scene_dir, &mut |f| {
        bar.set_position(f as u64 + 1)
    })?;
    bar.finish();

    // 2. Training.
    println!("2/4 training");
    let train = AutoencoderArgs {
        data: out.join("data"),
        config: Some(config.clone()),
        run: RunArgs {
            out: out.join("train"),
            steps: Some(steps),
            seed: Some(args.seed),
            resume: false,
            init: None,
            steps_per_scene: None,
            accumulate: None,
            checkpoint_every: steps,
            plot_every: 10,
            cooldown: Some(steps / 4),
            stop_at: None,
            precision: None,
            overlap: None,
        },
    };
    let summary = train_autoencoder(&gpu, &train, &Interrupt::never(), &SingleProcess)?;
    let (first_loss, last_loss) = (summary.first.losses.total(), summary.last.losses.total());

    // 3. Decoding: surface points of three frames, Gaussians of every frame (what the viewer
    // plays).
    println!("3/4 decoding surface points of frames 0, 12 and 23, and Gaussians of every frame");
    let decoded = out.join("decoded");
    std::fs::create_dir_all(&decoded).map_err(|e| format!("creating {}: {e}", decoded.display()))?;
    let ae = Autoencoder::load(&gpu, &summary.checkpoint)?;
    let cloud = read_cloud(&scene_dir)?;
    let encode_start = Instant::now();
    let decoding = Decoding::encode(&ae, &cloud, 0)?;
    let encode_seconds = encode_start.elapsed().as_secs_f64();
    let frames = [0, 12, 23];
    // Sampling costs points x steps: the decoded and measured sets grow with the scene.
    let decoded_points = Sampling::heun((points / 4).clamp(256, 4000));
    let chamfer_points = Sampling::heun((points / 8).clamp(256, 2000));
    let all: Vec<usize> = (0..FRAMES).collect();
    let bar = progress(frames.len() + all.len(), "frames");
    let mut on_frame = |_| bar.inc(1);
    decoding.write_frames(&frames, FrameOutput::Points, &decoded_points, &decoded, &mut on_frame)?;
    let gaussians = FrameOutput::Gaussians(VoxelSource::Input);
    let written = decoding.write_frames(&all, gaussians, &decoded_points, &decoded, &mut on_frame)?;
    // decode.json names the scene, so the viewer shows its truth and cameras beside the frames.
    let record = DecodeRecord {
        command: "decode gaussians",
        checkpoint: &summary.checkpoint,
        cloud: &scene_dir,
        ae: &ae,
        input_points: cloud.len() / CHANNELS,
        voxels: Some(VoxelSource::Input),
        sampling: &decoded_points,
        encode_seconds,
    };
    write_report(&decoded, &record, &written)?;
    bar.finish_and_clear();
    // Every other frame of the clip, the Gaussians over the input cloud's voxels.
    let every_other: Vec<usize> = (0..FRAMES).step_by(2).collect();
    // Rendered from the files just written, not decoded again.
    let render_frame = |f: usize, camera: &Camera, bg| render_written(&gpu, &written, f, camera, bg);
    clip_gif(&scene_dir, &every_other, render_frame, &out.join("decoded.gif"), 80, None)?;

    // 4. Renders beside the ground truth, and the metrics.
    println!("4/4 rendering and measuring");
    let eval = out.join("eval");
    std::fs::create_dir_all(&eval).map_err(|e| format!("creating {}: {e}", eval.display()))?;
    let scenes = SceneFolders::open(&gpu, &out.join("data"))?;
    let options = ReconOptions {
        views: Some(4),
        frame_step: 6,
        sampling: chamfer_points,
        voxels: vec![VoxelSource::Input],
        images: 6,
        seed: 0,
    };
    let report = recon(
        &ae,
        None,
        &scenes,
        &options,
        &eval,
        &eval.join("eval.json"),
        &summary.checkpoint,
        &out.join("data"),
    )?;
    let metrics = serde_json::to_value(&report)?;
    let summary_json = serde_json::json!({
        "device": gpu.caps().name,
        "config": config,
        "steps": steps,
        "resolution": res,
        "points": points,
        "first_loss": first_loss,
        "last_loss": last_loss,
        "train_seconds": summary.seconds,
        "total_seconds": started.elapsed().as_secs_f64(),
        "metrics": metrics["mean"],
    });
    write_bytes(&out.join(MARKER), serde_json::to_string_pretty(&summary_json)?.as_bytes())?;
    let figure = |k: &str, digits: usize| {
        metrics["mean"][k].as_f64().map(|v| format!("{v:.digits$}")).unwrap_or_else(|| "-".into())
    };
    println!(
        "\nDone in {:.0} s. Training took the loss from {:.4} to {:.4}; mean PSNR {} dB, SSIM {}, \
         Chamfer {} (the ground truth's halves against each other: {}).",
        started.elapsed().as_secs_f64(),
        first_loss,
        last_loss,
        figure("psnr", 2),
        figure("ssim", 3),
        figure("chamfer", 5),
        figure("chamfer_gt_halves", 5)
    );
    println!("Outputs in {}:", out.display());
    println!("  data/scene_00000/        the scene: 4D point cloud, supervision views, cameras, tracks");
    println!("  train/loss.png           the loss plot (log.jsonl holds every step, checkpoint.safetensors the model)");
    println!("  decoded/points_fFF.ply   decoded surface points of frames 0, 12, 23");
    println!(
        "  decoded/gaussians_fFF.ply  decoded 3D Gaussians of every frame (3D Gaussian splatting layout)"
    );
    println!(
        "  decoded.gif              the clip: ground truth | decoded Gaussians, from a supervision view"
    );
    println!("  eval/*.png               renders: ground truth | ours");
    println!("  eval/eval.json           PSNR, SSIM and Chamfer per frame and view; {MARKER}: this summary");
    let exe = std::env::args().next().unwrap_or_else(|| "velox".into());
    println!(
        "Watch the decoded clip beside the ground truth's points, from the scene's cameras, in a browser:\n  \
         {exe} view {}",
        decoded.display()
    );
    Ok(())
}
