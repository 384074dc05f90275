//! `velox data`: makes training scenes (procedural or from glTF files) in the format of
//! `velox_data::format`, with a progress bar over the frames of all scenes.
//!
//! A scene is rendered into `NAME.partial` and renamed when complete. A file that cannot be
//! imported is reported with its name and the problem, and the other scenes are still made;
//! the command fails at the end if any scene failed.

use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::builder::RangedU64ValueParser;
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use velox_data::format::write_scene;
use velox_data::pipeline::{MAX_POINTS, MAX_TRACKS};
use velox_data::procedural::FRAMES;
use velox_data::{gltf_import, procedural, AnimatedMesh, SynthOptions};
use velox_engine::Gpu;

use crate::CliResult;

#[derive(Subcommand)]
pub enum DataCommand {
    /// Procedural animated scenes: walkers, arms, pendulums, deforming and rigid shapes.
    Synth {
        #[command(flatten)]
        common: CommonArgs,
        /// Number of scenes, 1 to 1000000.
        #[arg(long, default_value_t = 8, value_parser = RangedU64ValueParser::<usize>::new().range(1..=1_000_000))]
        scenes: usize,
        /// Seed of the first scene; scene i uses seed + i.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Folder of PNG/JPEG images to crop textures from (else procedural textures only).
        #[arg(long)]
        textures: Option<PathBuf>,
    },
    /// Cloth scenes: a random t-shirt, pair of shorts or towel, folded once or twice, lifted and
    /// dropped, simulated by the engine's cloth solver; each scene also has `cloth.json` (the
    /// garment, its folds and drop height, and the simulated centre of mass per frame).
    Cloth {
        #[command(flatten)]
        common: CommonArgs,
        /// Number of scenes, 1 to 1000000.
        #[arg(long, default_value_t = 8, value_parser = RangedU64ValueParser::<usize>::new().range(1..=1_000_000))]
        scenes: usize,
        /// Which split: its scenes draw from seeds no other split uses, so splits never share
        /// a garment shape or a texture.
        #[arg(long, value_enum, default_value_t = Split::Train)]
        split: Split,
        /// Seed of the first scene within the split; scene i uses seed + i.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Folder of PNG/JPEG images to crop textures from (else procedural textures only).
        #[arg(long)]
        textures: Option<PathBuf>,
    },
    /// Scenes from glTF 2.0 files (.gltf or .glb), one per file.
    Gltf {
        /// The files to import.
        #[arg(required = true)]
        files: Vec<PathBuf>,
        #[command(flatten)]
        common: CommonArgs,
        /// Which animation to sample (default: the first).
        #[arg(long)]
        animation: Option<usize>,
        /// Seed for the cameras, point sample and tracks.
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
}

#[derive(Args)]
pub struct CommonArgs {
    /// Output folder (one sub-folder per scene).
    #[arg(long)]
    out: PathBuf,
    /// Image side of every view.
    #[arg(long, default_value_t = 128, value_parser = clap::value_parser!(u32).range(8..=2048))]
    res: u32,
    /// Points in each scene's 4D point cloud, 1 to 16777216.
    #[arg(long, default_value_t = 200_000,
          value_parser = RangedU64ValueParser::<usize>::new().range(1..=MAX_POINTS as u64))]
    points: usize,
    /// Tracked surface points per scene, 0 to 1048576. Tracks start on distinct surface
    /// pixels of frame 0 over the input views: a scene that shows fewer pixels gets one track
    /// per pixel, and a note says so.
    #[arg(long, default_value_t = 1024,
          value_parser = RangedU64ValueParser::<usize>::new().range(0..=MAX_TRACKS as u64))]
    tracks: usize,
    /// Supersampling factor of the anti-aliased views.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=4))]
    supersample: u32,
}

/// The splits of `velox data cloth`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    /// Where the split's seeds start: 2^40 apart, so no two splits share one.
    fn base(self) -> u64 {
        match self {
            Split::Train => 0,
            Split::Val => 1 << 40,
            Split::Test => 2 << 40,
        }
    }
}

/// What a job makes: the mesh, a description, and files to write beside the scene's.
struct Made {
    mesh: AnimatedMesh,
    detail: Option<String>,
    extra: Vec<(&'static str, Vec<u8>)>,
    /// What the source did that the import tolerated, said as the scene is written.
    warnings: Vec<String>,
}

/// How a job gets its mesh (on the device, for the simulated ones).
type Make = Box<dyn FnOnce(&Gpu) -> CliResult<Made>>;

/// One scene to make: its folder name, a description, a seed and how to get its mesh.
struct Job {
    name: String,
    source: String,
    seed: u64,
    make: Make,
}

pub fn run(cmd: DataCommand) -> CliResult<()> {
    let (common, jobs): (CommonArgs, Vec<Job>) = match cmd {
        DataCommand::Synth { common, scenes, seed, textures } => {
            let folder = textures.as_deref().map(velox_data::texture::ImageFolder::open).transpose()?;
            let folder = folder.map(std::sync::Arc::new);
            let jobs = (0..scenes as u64)
                .map(|i| {
                    let s = seed + i;
                    let folder = folder.clone();
                    Job {
                        name: format!("scene_{s:05}"),
                        source: format!("procedural seed {s}"),
                        seed: s,
                        make: Box::new(move |_| {
                            let (recipe, mesh) = procedural::scene(s, folder.as_deref())?;
                            Ok(Made {
                                mesh,
                                detail: Some(recipe.objects.join(", ")),
                                extra: Vec::new(),
                                warnings: Vec::new(),
                            })
                        }),
                    }
                })
                .collect();
            (common, jobs)
        }
        DataCommand::Cloth { common, scenes, split, seed, textures } => {
            let folder = textures.as_deref().map(velox_data::texture::ImageFolder::open).transpose()?;
            let folder = folder.map(std::sync::Arc::new);
            let jobs = (0..scenes as u64)
                .map(|i| {
                    let s = split.base() + seed + i;
                    let folder = folder.clone();
                    Job {
                        name: format!("cloth_{:05}", seed + i),
                        source: format!("cloth seed {s}"),
                        seed: s,
                        make: Box::new(move |gpu| {
                            let (mesh, record) = velox_data::cloth::scene(gpu, s, folder.as_deref())?;
                            let detail = format!(
                                "{:?}, {} fold(s), dropped from {:.2}",
                                record.kind, record.folds, record.drop_height
                            )
                            .to_lowercase();
                            let json = serde_json::to_string_pretty(&record)?.into_bytes();
                            Ok(Made {
                                mesh,
                                detail: Some(detail),
                                extra: vec![("cloth.json", json)],
                                warnings: Vec::new(),
                            })
                        }),
                    }
                })
                .collect();
            (common, jobs)
        }
        DataCommand::Gltf { files, common, animation, seed } => {
            let jobs = files
                .into_iter()
                .enumerate()
                .map(|(i, file)| {
                    let stem = file.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
                    Job {
                        name: format!("{stem}_{i:03}"),
                        source: file.display().to_string(),
                        seed: seed + i as u64,
                        make: Box::new(move |_| {
                            let imported = gltf_import::import(&file, animation)?;
                            Ok(Made {
                                mesh: imported.mesh,
                                detail: imported.credits,
                                extra: Vec::new(),
                                warnings: imported.warnings,
                            })
                        }),
                    }
                })
                .collect();
            (common, jobs)
        }
    };
    std::fs::create_dir_all(&common.out).map_err(|e| format!("{}: {e}", common.out.display()))?;
    let gpu = Gpu::new()?;
    let opts = SynthOptions {
        res: common.res,
        points: common.points,
        supersample: common.supersample,
        tracks: common.tracks,
    };
    let bar = ProgressBar::new((jobs.len() * FRAMES) as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames  {elapsed} (eta {eta})  {msg}")
            .expect("a valid template"),
    );
    let start = Instant::now();
    let mut failed = Vec::new();
    let mut written = 0;
    for job in jobs {
        bar.set_message(job.name.clone());
        match make_scene(&gpu, job, &opts, &common.out, &bar) {
            Ok(()) => written += 1,
            Err(e) => {
                bar.suspend(|| eprintln!("error: {e}"));
                failed.push(e);
            }
        }
    }
    bar.finish_with_message("done");
    println!(
        "wrote {written} scene(s) to {} in {:.1} s",
        common.out.display(),
        start.elapsed().as_secs_f64()
    );
    if !failed.is_empty() {
        return Err(format!("{} scene(s) failed; see the errors above", failed.len()).into());
    }
    Ok(())
}

fn make_scene(gpu: &Gpu, job: Job, opts: &SynthOptions, out: &Path, bar: &ProgressBar) -> CliResult<()> {
    let start_pos = bar.position();
    let made = (job.make)(gpu).map_err(|e| format!("{}: {e}", job.source))?;
    for w in &made.warnings {
        bar.suspend(|| eprintln!("warning: {}: {w}", job.source));
    }
    let dir = out.join(&job.name);
    let meta = write_scene(gpu, &made.mesh, &job.source, made.detail, job.seed, opts, &dir, &mut |f| {
        bar.set_position(start_pos + f as u64 + 1)
    })
    .map_err(|e| format!("{}: {e}", job.source))?;
    for (file, bytes) in &made.extra {
        velox_io::write_bytes(&dir.join(file), bytes)?;
    }
    if meta.tracks < opts.tracks {
        bar.suspend(|| {
            eprintln!(
                "note: {}: {} tracks of the {} asked for: frame 0 shows only {} surface pixels over the input views",
                job.name, meta.tracks, opts.tracks, meta.tracks
            )
        });
    }
    Ok(())
}
