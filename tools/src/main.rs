//! The `velox` command.

mod bench;
mod data;
mod decode;
mod demo;
mod eval;
mod info;
mod render;

use clap::{Parser, Subcommand};

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
    },
    /// Run the demo on whatever device is present: device report and a quick kernel benchmark.
    Demo {
        /// Folder for the demo's outputs.
        #[arg(long, default_value = "velox-demo")]
        out: std::path::PathBuf,
    },
    /// Training data: procedural animated scenes and glTF imports, rendered to point clouds,
    /// images, occupancy and tracks.
    Data {
        #[command(subcommand)]
        what: data::DataCommand,
    },
    /// Render Gaussians (a 3D Gaussian splatting PLY) from a camera orbit to PNG frames and
    /// depth EXRs.
    Render(render::RenderArgs),
    /// Encode a 4D point cloud with a trained autoencoder and decode surface points or
    /// Gaussians per frame to PLY.
    Decode {
        #[command(subcommand)]
        what: decode::DecodeCommand,
    },
    /// Evaluate a trained autoencoder: PSNR, SSIM and Chamfer on held-out scenes.
    Eval {
        #[command(subcommand)]
        what: eval::EvalCommand,
    },
    /// Benchmarks: GPU time against error.
    Bench {
        #[command(subcommand)]
        what: bench::BenchCommand,
    },
}

fn main() {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Info { json } => info::run(json.as_deref()),
        Command::Demo { out } => demo::run(&out),
        Command::Render(args) => render::run(&args),
        Command::Bench { what } => bench::run(what),
        Command::Data { what } => data::run(what),
        Command::Decode { what } => decode::run(what),
        Command::Eval { what } => eval::run(what),
    };
    if let Err(e) = result {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

/// Errors of the command: engine errors and I/O, each with what was being done.
pub type CliResult<T> = Result<T, Box<dyn std::error::Error>>;
