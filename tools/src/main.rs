//! The `velox` command.

mod batch;
mod bench;
mod data;
mod decode;
mod demo;
mod encode;
mod eval;
mod export;
mod generate;
mod import;
mod info;
mod interrupt;
mod overlay;
mod render;
mod track;
mod train;
mod view;

use clap::{Parser, Subcommand};
use velox_models::Model;

#[derive(Parser)]
#[command(name = "velox", version, about = "Velox 4D dynamic tokens on a Vulkan compute runtime")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Show the Vulkan devices, the one chosen (VELOX_DEVICE overrides), its features and
    /// limits, and which kernel variants it will use.
    Info {
        /// Also write the report as JSON to this file.
        #[arg(long)]
        json: Option<std::path::PathBuf>,
        /// Also run one dispatch that measures the subgroups the device really runs (some
        /// drivers report another size than they run; the kernels count their lanes).
        #[arg(long)]
        probe: bool,
    },
    /// The demo, on whatever device is present: make a scene, train a small autoencoder on it,
    /// decode its points and Gaussians, render and measure them.
    Demo(demo::DemoArgs),
    /// Training data: procedural animated scenes, glTF imports and simulated cloth, rendered to
    /// point clouds, images, occupancy and tracks.
    Data {
        #[command(subcommand)]
        what: data::DataCommand,
    },
    /// Captures of the world made into the project's formats: an RGBD capture into the
    /// tracker's video.
    Import {
        #[command(subcommand)]
        what: import::ImportCommand,
    },
    /// Print a model's config as JSON (paper, small, tiny, a JSON file, or the config a
    /// .safetensors checkpoint was trained with): a start for a config file of one's own.
    Config {
        /// The config's name or path.
        #[arg(default_value = "small")]
        name: String,
        /// Which model's config (a checkpoint names its own).
        #[arg(long, value_enum, default_value_t = ConfigModel::Autoencoder)]
        model: ConfigModel,
        /// Print the parameter count of each part of the model and the total instead (counted
        /// from the parameter declarations, on any device: nothing as large as a parameter is
        /// allocated).
        #[arg(long)]
        params: bool,
    },
    /// Train a Velox model.
    Train {
        #[command(subcommand)]
        what: train::TrainCommand,
    },
    /// Render Gaussians (a 3D Gaussian splatting PLY, its spherical harmonics of degree 0 to 3
    /// along each view) from a camera orbit to PNG frames and depth EXRs.
    Render(render::RenderArgs),
    /// Watch a 4D result in a browser: serves a WebGL2 viewer of per-frame Gaussians (decode,
    /// generate), decoded points or a dataset scene on 127.0.0.1, with a time slider, orbit
    /// controls and the scene's cameras; or writes it as one HTML file (--html).
    View(view::ViewArgs),
    /// Write per-frame Gaussians (a decode or generate output) in the formats other viewers
    /// play: a numbered PLY sequence (SuperSplat), a .splatv flipbook (splaTV, gsplat.js), SPZ
    /// or glTF with KHR_gaussian_splatting, one file a frame.
    Export(export::ExportArgs),
    /// Encode every scene of a dataset once with a trained autoencoder's encoder and store the
    /// tokens beside it (k x token_dim per scene, with their query points, the checkpoint's
    /// hash and the dataset's token statistics), for the models that train on them.
    Encode(encode::EncodeArgs),
    /// Track query points through an RGBD video with a trained tracker: tracks as JSON and
    /// PLY per frame, and the video's frames with the tracks drawn over them.
    Track(track::TrackArgs),
    /// Generate the dynamic tokens of the object a video (or an image) shows with a trained
    /// generator, decode its Gaussians frame by frame and render them from the input view and
    /// from views around it, with a contact sheet.
    Generate(generate::GenerateArgs),
    /// Encode a 4D point cloud with a trained autoencoder and decode surface points or
    /// Gaussians per frame to PLY.
    Decode {
        #[command(subcommand)]
        what: decode::DecodeCommand,
    },
    /// Evaluate a trained model: the autoencoder's reconstructions, the voxel decoder, the
    /// tracker, the generator's scenes and the physics of its cloth.
    Eval {
        #[command(subcommand)]
        what: eval::EvalCommand,
    },
    /// Write a checkpoint's parameters alone as a weights file (f16 by default: a quarter of the
    /// checkpoint's size), split into parts of at most --max-part-mib where larger; decode,
    /// encode, eval, track, generate and --init load it as they load a checkpoint.
    Weights {
        /// The checkpoint (or weights file) to read.
        checkpoint: std::path::PathBuf,
        /// The weights file to write (a name ending in .safetensors; parts are named
        /// NAME-00001-of-0000N.safetensors beside it).
        #[arg(long)]
        out: std::path::PathBuf,
        /// The number type of the tensors written.
        #[arg(long, value_enum, default_value = "f16")]
        dtype: WeightsDtypeArg,
        /// Split into parts of at most this many MiB.
        #[arg(long, value_parser = clap::value_parser!(u64).range(1..=1 << 20))]
        max_part_mib: Option<u64>,
    },
    /// Benchmarks: GPU time against error.
    Bench {
        #[command(subcommand)]
        what: bench::BenchCommand,
    },
}

/// The number types `velox weights` writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum WeightsDtypeArg {
    F16,
    F32,
}

fn write_weights(
    checkpoint: &std::path::Path,
    out: &std::path::Path,
    dtype: WeightsDtypeArg,
    max_part_mib: Option<u64>,
) -> CliResult<()> {
    use velox_models::checkpoint::{save_weights, WeightsDtype};
    let dtype = match dtype {
        WeightsDtypeArg::F16 => WeightsDtype::F16,
        WeightsDtypeArg::F32 => WeightsDtype::F32,
    };
    let written = save_weights(checkpoint, out, dtype, max_part_mib.map(|m| m << 20))?;
    for path in &written {
        let bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
        println!("wrote {} ({:.2} MiB)", path.display(), bytes as f64 / (1 << 20) as f64);
    }
    Ok(())
}

/// The models `velox config` knows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum ConfigModel {
    Autoencoder,
    Voxels,
    Tracker,
    Generator,
}

fn print_config(name: &str, model: ConfigModel, params: bool) -> CliResult<()> {
    use velox_models::velox::{autoencoder::Autoencoder, count, tracker::Tracker, voxels::VoxelDecoder};
    let path = std::path::Path::new(name);
    let checkpoint = path.extension().is_some_and(|e| e == "safetensors");
    // A checkpoint says which model it holds.
    let model = match checkpoint {
        true => match velox_models::checkpoint::config_json(path)?["model"].as_str() {
            Some(velox_models::velox::voxels::MODEL_KIND) => ConfigModel::Voxels,
            Some(velox_models::velox::tracker::MODEL_KIND) => ConfigModel::Tracker,
            Some(velox_models::velox::generator::MODEL_KIND) => ConfigModel::Generator,
            _ => ConfigModel::Autoencoder,
        },
        false => model,
    };
    let row =
        |part: &str, n: usize| format!("  {part:<18} {:>14}  ({:.2} M)\n", thousands(n), n as f64 / 1e6);
    let text = match model {
        ConfigModel::Autoencoder => {
            let cfg = match checkpoint {
                true => Autoencoder::checkpoint_config(path)?,
                false => velox_models::config::AutoencoderConfig::named(name)?,
            };
            if params {
                let c = count::parameter_counts(&velox_engine::Gpu::new()?, &cfg)?;
                format!(
                    "parameters of the {} autoencoder:\n{}{}{}{}",
                    cfg.name,
                    row("encoder", c.encoder),
                    row("surface decoder", c.surface),
                    row("Gaussian decoder", c.gaussians),
                    row("total", c.total)
                )
            } else {
                serde_json::to_string_pretty(&cfg)? + "\n"
            }
        }
        ConfigModel::Voxels => {
            let cfg = match checkpoint {
                true => VoxelDecoder::checkpoint_config(path)?,
                false => velox_models::config::VoxelConfig::named(name)?,
            };
            if params {
                let c = count::voxel_parameter_counts(&velox_engine::Gpu::new()?, &cfg)?;
                format!(
                    "parameters of the {} voxel decoder:\n{}{}{}",
                    cfg.name,
                    row("coarse stage", c.coarse),
                    row("fine stage", c.fine),
                    row("total", c.total)
                )
            } else {
                serde_json::to_string_pretty(&cfg)? + "\n"
            }
        }
        ConfigModel::Tracker => {
            let cfg = match checkpoint {
                true => Tracker::checkpoint_config(path)?,
                false => velox_models::config::TrackerConfig::named(name)?,
            };
            if params {
                let b = Tracker::declare(&velox_engine::Gpu::new()?, &cfg)?;
                format!("parameters of the {} tracker:\n{}", cfg.name, row("total", b.num_parameters()))
            } else {
                serde_json::to_string_pretty(&cfg)? + "\n"
            }
        }
        ConfigModel::Generator => {
            use velox_models::velox::generator::Generator;
            let cfg = match checkpoint {
                true => Generator::checkpoint_config(path)?,
                false => velox_models::config::GeneratorConfig::named(name)?,
            };
            if params {
                let b = Generator::declare(&velox_engine::Gpu::new()?, &cfg)?;
                let total = b.num_parameters();
                let blocks = b.num_parameters_under("blocks.");
                let condition = b.num_parameters_under("rgb.") + b.num_parameters_under("cond.");
                format!(
                    "parameters of the {} generator:\n{}{}{}{}",
                    cfg.name,
                    row("blocks", blocks),
                    row("condition", condition),
                    row("embeddings, head", total - blocks - condition),
                    row("total", total)
                )
            } else {
                serde_json::to_string_pretty(&cfg)? + "\n"
            }
        }
    };
    // Written, not printed: a reader that stops early (`| head`) is not an error.
    use std::io::Write;
    match write!(std::io::stdout().lock(), "{text}") {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(()),
    }
}

/// 1234567 as "1,234,567".
fn thousands(n: usize) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

fn main() {
    ignore_file_size_signal();
    let result = dispatch(Cli::parse().command);
    if let Some(table) = velox_engine::profile::report() {
        eprintln!("\n{table}");
    }
    if let Err(e) = result {
        // A run stopped by a signal says where its work is and exits as the signal would.
        if let Some(stop) = e.downcast_ref::<interrupt::Interrupted>() {
            eprintln!("{stop}");
            std::process::exit(stop.exit_code());
        }
        eprintln!("error: {}", message(&*e));
        std::process::exit(1);
    }
    // Under VELOX_VALIDATE, a validation error anywhere fails the command, even one the work
    // above did not trip over (a message after the last submit).
    let errors = velox_engine::validation::error_count();
    if errors > 0 {
        eprintln!("error: the Vulkan validation layer reported {errors} error(s); the first:");
        for line in velox_engine::validation::first_errors().iter().take(3) {
            eprintln!("  {line}");
        }
        std::process::exit(1);
    }
}

/// A write past the file size limit (`ulimit -f`) raises SIGXFSZ, which ends the process
/// without a word and leaves the temporary file behind. Ignored, the write fails with EFBIG
/// instead, and the error names the file (see `velox_io::write_atomically`).
fn ignore_file_size_signal() {
    #[cfg(unix)]
    // SAFETY: SIG_IGN installs no handler code; nothing else in the program handles SIGXFSZ.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
    }
}

fn dispatch(command: Command) -> CliResult<()> {
    match command {
        Command::Info { json, probe } => info::run(json.as_deref(), probe),
        Command::Demo(args) => demo::run(&args),
        Command::Render(args) => render::run(&args),
        Command::View(args) => view::run(&args),
        Command::Export(args) => export::run(&args),
        Command::Bench { what } => bench::run(what),
        Command::Data { what } => data::run(what),
        Command::Import { what } => import::run(what),
        Command::Config { name, model, params } => print_config(&name, model, params),
        Command::Train { what } => train::run(what),
        Command::Encode(args) => encode::run(&args),
        Command::Track(args) => track::run(&args),
        Command::Generate(args) => generate::run(&args),
        Command::Decode { what } => decode::run(what),
        Command::Eval { what } => eval::run(what),
        Command::Weights { checkpoint, out, dtype, max_part_mib } => {
            write_weights(&checkpoint, &out, dtype, max_part_mib)
        }
    }
}

/// Errors of the command: engine errors and I/O, each with what was being done.
pub type CliResult<T> = Result<T, Box<dyn std::error::Error>>;

/// An error as the command says it: the library's settings named as this command's flags
/// (`velox_engine::Error::Setting`'s `{stop_at}` as `--stop-at`).
pub fn message(e: &(dyn std::error::Error + 'static)) -> String {
    let engine =
        e.downcast_ref::<velox_engine::Error>().or(match e.downcast_ref::<velox_data::DataError>() {
            Some(velox_data::DataError::Engine(inner)) => Some(inner),
            _ => None,
        });
    match engine {
        Some(inner) => inner.spelled(|setting| format!("--{}", setting.replace('_', "-"))),
        None => e.to_string(),
    }
}
