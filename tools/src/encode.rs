//! `velox encode`: a trained autoencoder's encoder over every scene of a dataset, once, the
//! tokens stored beside the scenes for the models that train on them with the encoder frozen.
//! `velox_tasks::encode` does the work (its docs say what a re-run keeps and what it refuses),
//! `velox_models::velox::tokens` gives the folder's layout; this parses, shows progress and
//! prints the summary.

use std::path::PathBuf;

use indicatif::ProgressBar;
use velox_engine::Gpu;
use velox_models::velox::tokens::CloudSource;
use velox_tasks::encode::{encode_dataset, EncodeObserver, EncodeOptions};

use crate::decode::{progress, PrecisionArg};
use crate::CliResult;

#[derive(clap::Args)]
pub struct EncodeArgs {
    /// Autoencoder checkpoint whose encoder encodes (safetensors, as training writes it).
    #[arg(long)]
    checkpoint: PathBuf,
    /// Dataset folder (scenes as `velox data` writes them).
    #[arg(long)]
    data: PathBuf,
    /// Token folder [default: DATA/tokens, or DATA/tokens-video with --source video].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Seed of the encoder's queries.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Precision of the encoder: f32, or f16 (matrix products and attention on f16 operands
    /// with f32 accumulation).
    #[arg(long, value_enum, default_value_t = PrecisionArg::F32)]
    precision: PrecisionArg,
    /// Encode every scene again, and replace tokens of another checkpoint, seed or precision
    /// (refused without it).
    #[arg(long)]
    force: bool,
    /// The cloud to encode: the scenes' point clouds (for the voxel decoder and the
    /// generators), or their RGBD videos back-projected (the tracker's input).
    #[arg(long, value_enum, default_value_t = SourceArg::Points)]
    source: SourceArg,
    /// With --source video: at most this many of a video's surface pixels (a seeded draw).
    #[arg(long, default_value_t = velox_data::rgbd::DEFAULT_POINTS as u64, value_parser = clap::value_parser!(u64).range(1..=16_777_216))]
    video_points: u64,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum SourceArg {
    Points,
    Video,
}

/// The progress bar over the scenes to encode.
#[derive(Default)]
struct Bar(Option<ProgressBar>);

impl EncodeObserver for Bar {
    fn start(&mut self, to_encode: usize, kept: usize) {
        if kept > 0 {
            println!("{kept} scenes are encoded already with this checkpoint, seed and precision: kept");
        }
        self.0 = Some(progress(to_encode, "scenes"));
    }

    fn encoded(&mut self, name: &str) {
        if let Some(bar) = &self.0 {
            bar.set_message(name.to_string());
            bar.inc(1);
        }
    }
}

/// The least and the most of `v`.
fn range(v: &[f64]) -> String {
    let (lo, hi) = v.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| (lo.min(x), hi.max(x)));
    format!("{lo:.4} to {hi:.4}")
}

pub fn run(a: &EncodeArgs) -> CliResult<()> {
    let gpu = Gpu::new()?;
    let options = EncodeOptions {
        checkpoint: a.checkpoint.clone(),
        data: a.data.clone(),
        out: a.out.clone(),
        seed: a.seed,
        precision: a.precision.into(),
        force: a.force,
        source: match a.source {
            SourceArg::Points => CloudSource::Points,
            SourceArg::Video => CloudSource::Video,
        },
        video_points: a.video_points as usize,
    };
    println!(
        "encoding the {} of the scenes of {} with the encoder of {} ({}, seed {}) into {} on {}",
        match options.source {
            CloudSource::Points => "point clouds",
            CloudSource::Video => "RGBD videos",
        },
        a.data.display(),
        a.checkpoint.display(),
        options.precision.name(),
        a.seed,
        options.out_dir().display(),
        gpu.caps().name
    );
    let mut bar = Bar::default();
    let result = encode_dataset(&gpu, &options, &mut bar);
    if let Some(b) = &bar.0 {
        b.finish_and_clear();
    }
    let r = result?;
    let m = &r.manifest;
    if let Some(replaced) = &r.replaced {
        println!("replaced what {} held: {replaced}", r.dir.display());
    }
    println!(
        "encoded {} scenes ({} points) in {:.1} s, kept {}: {} scenes of {} tokens x {} with the {} autoencoder \
         (checkpoint hash {})",
        r.encoded.len(),
        r.points,
        r.encode_seconds,
        r.kept.len(),
        m.scenes.len(),
        m.tokens,
        m.token_dim,
        m.origin.config.name,
        m.origin.checkpoint_hash
    );
    println!("token statistics per channel: mean {}, standard deviation {}", range(&m.mean), range(&m.std));
    println!(
        "wrote {} (the scenes, the encoder's origin, the statistics) beside the scene files",
        r.dir.join(velox_models::velox::tokens::MANIFEST).display()
    );
    Ok(())
}
