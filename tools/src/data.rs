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
use velox_data::{procedural, AnimatedMesh, SynthOptions};
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
    /// Scenes from glTF 2.0 files (.gltf or .glb), one per file: files, folders (searched
    /// recursively, in name order) and lists of files. Files are imported on every core while
    /// the scenes render; a file that fails is reported and the others are still made; a
    /// re-run keeps the scenes already written. `OUT/report.json` lists every file: its
    /// scene, whether it was written, kept or failed (and why), and its warnings.
    Gltf {
        /// Files and folders to import.
        files: Vec<PathBuf>,
        /// A text file listing files or folders to import, one per line (relative to the
        /// list's folder; blank lines and lines starting with # are skipped).
        #[arg(long)]
        list: Option<PathBuf>,
        /// Files imported at once [default: the machine's cores]. The scenes do not depend on it.
        #[arg(long, value_parser = RangedU64ValueParser::<usize>::new().range(1..=1024))]
        jobs: Option<usize>,
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
    /// Background of the supervision views and the conditioning video as r,g,b in [0, 1]
    /// (a dark model shows on a light one); training and evaluation render on it.
    #[arg(long, default_value = "0,0,0", value_parser = crate::render::parse_vec3)]
    background: [f32; 3],
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
        DataCommand::Gltf { files, list, jobs, common, animation, seed } => {
            let files = crate::batch::gltf_files(&files, list.as_deref())?;
            let workers = jobs.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
            let names: Vec<String> = files
                .iter()
                .enumerate()
                .map(|(i, file)| {
                    let stem = file.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
                    format!("{stem}_{i:03}")
                })
                .collect();
            // A re-run keeps what an earlier one wrote: a scene is renamed into place only
            // when complete, so a folder with its meta.json is whole.
            let (kept, todo): (Vec<usize>, Vec<usize>) =
                (0..files.len()).partition(|&i| common.out.join(&names[i]).join("meta.json").is_file());
            let kept: Vec<(String, String)> =
                kept.into_iter().map(|i| (names[i].clone(), files[i].display().to_string())).collect();
            let imports = crate::batch::Imports::start(
                todo.iter().map(|&i| files[i].clone()).collect(),
                animation,
                workers,
            );
            let jobs = todo
                .iter()
                .enumerate()
                .map(|(k, &i)| {
                    let imports = imports.clone();
                    Job {
                        name: names[i].clone(),
                        source: files[i].display().to_string(),
                        seed: seed + i as u64,
                        make: Box::new(move |_| {
                            let imported = imports.take(k)?;
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
            return run_jobs(common, jobs, kept, Some(names));
        }
    };
    run_jobs(common, jobs, Vec::new(), None)
}

/// Makes the scenes of `jobs` under `common.out`; `kept` (scene, source) were written by an
/// earlier run. For a batch (every scene's name, in the order of its files), writes
/// `OUT/report.json`.
fn run_jobs(
    common: CommonArgs,
    jobs: Vec<Job>,
    kept: Vec<(String, String)>,
    batch: Option<Vec<String>>,
) -> CliResult<()> {
    std::fs::create_dir_all(&common.out).map_err(|e| format!("{}: {e}", common.out.display()))?;
    if !kept.is_empty() {
        println!(
            "keeping {} scene(s) already in {} (delete a scene's folder to make it again)",
            kept.len(),
            common.out.display()
        );
    }
    let gpu = Gpu::new()?;
    let opts = SynthOptions {
        res: common.res,
        points: common.points,
        supersample: common.supersample,
        tracks: common.tracks,
        background: common.background,
    };
    let bar = ProgressBar::new((jobs.len() * FRAMES) as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames  {elapsed} (eta {eta})  {msg}")
            .expect("a valid template"),
    );
    let start = Instant::now();
    let mut failed = Vec::new();
    let mut written = 0;
    // A batch stops after the scene under way on Ctrl-C, and writes its report.
    let interrupt = match batch {
        Some(_) => crate::interrupt::Interrupt::catch_saying(
            b"\nstopping after this scene to write the report (signal again to quit at once)\n",
        )?,
        None => crate::interrupt::Interrupt::never(),
    };
    let mut report: Vec<crate::batch::Entry> = kept
        .into_iter()
        .map(|(scene, file)| crate::batch::Entry {
            file,
            scene,
            status: "kept",
            reason: None,
            warnings: Vec::new(),
        })
        .collect();
    for job in jobs {
        if interrupt.requested().is_some() {
            break;
        }
        bar.set_message(job.name.clone());
        let (scene, file) = (job.name.clone(), job.source.clone());
        match make_scene(&gpu, job, &opts, &common.out, &bar) {
            Ok(warnings) => {
                written += 1;
                report.push(crate::batch::Entry { file, scene, status: "written", reason: None, warnings });
            }
            Err(e) => {
                bar.suspend(|| eprintln!("error: {e}"));
                let reason = Some(e.to_string());
                report.push(crate::batch::Entry {
                    file,
                    scene,
                    status: "failed",
                    reason,
                    warnings: Vec::new(),
                });
                failed.push(e);
            }
        }
    }
    bar.finish_with_message("done");
    let seconds = start.elapsed().as_secs_f64();
    println!("wrote {written} scene(s) to {} in {seconds:.1} s", common.out.display());
    if let Some(order) = batch {
        let files = order.len();
        let kept = report.iter().filter(|e| e.status == "kept").count();
        let left = files - written - kept - failed.len();
        let path = crate::batch::write_report(&common.out, report, &order, seconds)?;
        println!(
            "{files} file(s): {written} written, {kept} kept, {} failed{} ({:.1} files a minute); report: {}",
            failed.len(),
            if left > 0 { format!(", {left} not started") } else { String::new() },
            written as f64 / seconds.max(1e-9) * 60.0,
            path.display()
        );
    }
    if let Some(signal) = interrupt.requested() {
        let message = format!(
            "stopped by {}: the scenes written are whole; run the same command again to make the rest",
            crate::interrupt::signal_name(signal)
        );
        return Err(crate::interrupt::Interrupted { signal, message }.into());
    }
    if !failed.is_empty() {
        return Err(format!("{} scene(s) failed; see the errors above", failed.len()).into());
    }
    Ok(())
}

/// Makes one scene; returns the warnings of its source and of the scene written (a scene
/// a task cannot use: `format::scene_notes`).
fn make_scene(
    gpu: &Gpu,
    job: Job,
    opts: &SynthOptions,
    out: &Path,
    bar: &ProgressBar,
) -> CliResult<Vec<String>> {
    let start_pos = bar.position();
    let named = |e: String| if e.contains(&job.source) { e } else { format!("{}: {e}", job.source) };
    let made = (job.make)(gpu).map_err(|e| named(e.to_string()))?;
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
    let mut warnings = made.warnings;
    for (severity, note) in velox_data::format::scene_notes(&meta, opts.tracks) {
        let said = match severity {
            velox_data::format::Severity::Note => "note",
            velox_data::format::Severity::Warning => {
                warnings.push(note.clone());
                "warning"
            }
        };
        bar.suspend(|| eprintln!("{said}: {}: {note}", job.name));
    }
    Ok(warnings)
}
