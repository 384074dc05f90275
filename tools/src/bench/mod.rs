//! `velox bench`: GPU time against error, printed as a table and written as JSON records.

mod attention;
mod cloth;
mod kernels;
mod layers;
mod models;
mod raster;
mod report;
mod train;

use std::path::PathBuf;

use clap::Subcommand;
use serde::Serialize;
use velox_engine::stats::{max_abs_err, nmse};
use velox_engine::{Gpu, Recorder, Result};

use crate::CliResult;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Matmul (f32 and f16 inputs), softmax, scan, sort and scatter-add.
    Kernels(BenchArgs),
    /// Fused segment attention, forward and backward: dense, voxel-window self-attention,
    /// per-cell cross-attention and global cross-attention at the paper's sizes.
    Attention(BenchArgs),
    /// Each layer's forward and forward+backward: linear, RMSNorm, LayerNorm, SwiGLU and GELU
    /// feed-forwards at 8192 tokens of width 512, the Fourier embedding of 1.44 M points.
    Layers(BenchArgs),
    /// Gaussian rasteriser, forward and forward + backward, against the number of Gaussians
    /// and the resolution, on the scene gsplat is compared on; error against the reference.
    Raster(BenchArgs),
    /// The autoencoder's parts at the paper config with random weights: encoder (1.44 M
    /// points), Gaussian decoder (one frame), surface decoder (16384 points, 20 and 100 Heun
    /// steps), against the paper's H100 times.
    Models(BenchArgs),
    /// Cloth simulation: frames per second of a towel-sized sheet falling onto the ground, with
    /// and without self-collision.
    Cloth(BenchArgs),
    /// Training throughput: samples per second against the batch size for a config, with the
    /// step's time split into data, compute, all-reduce and optimiser.
    Train(TrainBenchArgs),
    /// A Markdown page of a folder of results (tools/device-check.sh's, tools/bench-all.sh's):
    /// the device, tests, every benchmark row beside PyTorch's time where
    /// tools/peers/torch_bench.py measured it, training and evaluation.
    Report(report::ReportArgs),
}

#[derive(clap::Args)]
pub struct TrainBenchArgs {
    #[command(flatten)]
    bench: BenchArgs,
    /// Model sizes: paper, small, tiny, or a JSON config file.
    #[arg(long, default_value = "small")]
    config: String,
    /// Batch sizes to time, comma-separated [default: 1,2,4 on a CPU device or with --quick,
    /// 1,2,4,8,16 on a GPU].
    #[arg(long, value_delimiter = ',', value_parser = clap::value_parser!(u16).range(1..=4096))]
    batches: Option<Vec<u16>>,
    /// Precisions of the training passes to time, comma-separated: f32, f16 (f16 operands with
    /// f32 accumulation, f32 master weights, a dynamic loss scale).
    #[arg(long, value_delimiter = ',', value_enum, default_value = "f32,f16")]
    precision: Vec<crate::decode::PrecisionArg>,
    /// The model to train: the autoencoder (against the batch), or one downstream of the
    /// encoder, on a scene's tokens.
    #[arg(long, value_enum, default_value = "autoencoder")]
    model: train::ModelArg,
    /// Record each autoencoder step while the last runs [default: the trainer's, on except on
    /// a CPU device]; where on, as many steps again are timed recorded apart ("apart ms").
    #[arg(long, value_enum)]
    overlap: Option<crate::train::OnOff>,
}

/// Which sizes a suite times.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SizeSet {
    /// The smallest: seconds on lavapipe.
    Quick,
    /// Sizes a CPU device times in minutes (the default there).
    Small,
    /// The paper's sizes (the default on GPUs).
    Large,
}

impl SizeSet {
    /// `--quick`, else `--sizes`, else the device's default.
    fn of(gpu: &Gpu, quick: bool, sizes: Option<SizeSet>) -> SizeSet {
        match (quick, sizes) {
            (true, _) => SizeSet::Quick,
            (false, Some(s)) => s,
            (false, None) if gpu.caps().kind == "CPU" => SizeSet::Small,
            (false, None) => SizeSet::Large,
        }
    }

    /// Whether the suite takes its small set (quick or small).
    pub fn small(self) -> bool {
        self != SizeSet::Large
    }
}

#[derive(clap::Args)]
pub struct BenchArgs {
    /// The quickest sizes (the same as --sizes quick).
    #[arg(long)]
    quick: bool,
    /// Which sizes to time, on any device [default: small on a CPU device such as lavapipe,
    /// large (the paper's) on a GPU].
    #[arg(long, value_enum)]
    sizes: Option<SizeSet>,
    /// PyTorch's times at the same shapes (tools/peers/torch_bench.py's or torch_cpu.py's JSON,
    /// from these records): each row is printed with PyTorch's time and the ratio.
    #[arg(long)]
    peer: Option<PathBuf>,
    /// Timed repeats per case (the median is reported).
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=1000))]
    repeats: u32,
    /// Write the records as JSON to this file.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// A benchmark suite: (device, sizes, repeats) -> records.
type Suite = fn(&Gpu, SizeSet, u32) -> Result<Vec<Record>>;

pub fn run(cmd: BenchCommand) -> CliResult<()> {
    let (args, which): (BenchArgs, Suite) = match cmd {
        BenchCommand::Train(t) => return run_train(t),
        BenchCommand::Report(a) => return report::run(&a),
        BenchCommand::Kernels(a) => (a, kernels::run),
        BenchCommand::Attention(a) => (a, attention::run),
        BenchCommand::Layers(a) => (a, layers::run),
        BenchCommand::Raster(a) => (a, raster::run),
        BenchCommand::Models(a) => (a, models::run),
        BenchCommand::Cloth(a) => (a, cloth::run),
    };
    let gpu = Gpu::new()?;
    keep_in(args.json.as_deref());
    load_peer(args.peer.as_deref())?;
    let records = which(&gpu, SizeSet::of(&gpu, args.quick, args.sizes), args.repeats)?;
    if let Some(path) = args.json {
        write_json(&path, &records)?;
    }
    Ok(())
}

/// Where the records of this run go as they come (`--json`), and those so far: each record is
/// written out as soon as it is measured, so a suite stopped part way (a time limit, a device
/// lost) leaves the records it finished.
static KEPT: std::sync::Mutex<Option<(PathBuf, Vec<Record>)>> = std::sync::Mutex::new(None);

fn keep_in(path: Option<&std::path::Path>) {
    *KEPT.lock().unwrap_or_else(|e| e.into_inner()) = path.map(|p| (p.to_path_buf(), Vec::new()));
}

/// Adds `r` to the records kept so far and rewrites the `--json` file with them (atomically;
/// nothing when no file was asked for). A write that fails here is reported by the final write.
pub fn keep(r: &Record) {
    let mut kept = KEPT.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((path, records)) = kept.as_mut() {
        records.push(r.clone());
        if let Ok(text) = serde_json::to_string_pretty(records) {
            let _ = velox_io::write_bytes(path, text.as_bytes());
        }
    }
}

fn run_train(t: TrainBenchArgs) -> CliResult<()> {
    let gpu = Gpu::new()?;
    keep_in(t.bench.json.as_deref());
    load_peer(t.bench.peer.as_deref())?;
    // The small sizes: --quick, --sizes quick or small, or a CPU device's default.
    let quick = SizeSet::of(&gpu, t.bench.quick, t.bench.sizes).small();
    let batches: Option<Vec<usize>> = t.batches.map(|b| b.into_iter().map(usize::from).collect());
    let precisions: Vec<velox_engine::Precision> = t.precision.into_iter().map(Into::into).collect();
    let records = match t.model {
        train::ModelArg::Autoencoder => {
            let overlap = t.overlap.map(|o| o == crate::train::OnOff::On);
            train::run(&gpu, quick, t.bench.repeats, &t.config, batches.as_deref(), &precisions, overlap)?
        }
        model => train::run_token_model(&gpu, model, quick, t.bench.repeats, &t.config, &precisions)?,
    };
    if let Some(path) = t.bench.json {
        write_json(&path, &records)?;
    }
    Ok(())
}

/// One benchmark result; the JSON schema of every `velox bench` command.
#[derive(Serialize, Clone, Debug)]
pub struct Record {
    pub name: String,
    pub shape: String,
    pub precision: String,
    pub device: String,
    pub median_ms: f64,
    pub min_ms: f64,
    pub repeats: u32,
    pub throughput: f64,
    pub throughput_unit: String,
    /// Throughput over the device's known peak for this kind of work, when known.
    pub peak_fraction: Option<f64>,
    pub nmse: f64,
    pub max_abs_err: f64,
    /// How the error was measured (full reference, or a sample of outputs).
    pub error_over: String,
    /// Whether times come from GPU timestamps (else wall clock around each submit).
    pub gpu_timed: bool,
    /// `bench train`: the mean step's milliseconds by part.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time_split_ms: Option<velox_models::train::trainer::TimeSplit>,
    /// `bench train`: the dispatches one step records, the most device memory the engine held
    /// during the timed steps, and one step's GPU milliseconds by kernel family.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dispatches_per_step: Option<u64>,
    /// `bench train`: the submissions a step makes, each one a host wait.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub submits_per_step: Option<u64>,
    /// `bench train`, where the trainer records a step while the last runs (a GPU): the
    /// median step's milliseconds without that overlap, the same steps recorded one after
    /// the other's wait.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub step_ms_unoverlapped: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub peak_memory_bytes: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub family_ms: Option<std::collections::BTreeMap<String, f64>>,
    /// The case's arithmetic: floating-point operations (a multiply-add is two, an exp one).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub flops: Option<f64>,
    /// The case's compulsory global-memory traffic: every input read once and every output
    /// written once. With `flops` it gives the arithmetic intensity, and with the device's peaks
    /// the roofline bound: no kernel can take less time than `bound_ms`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bytes: Option<f64>,
    /// The shortest time the device's peaks allow for `flops` and `bytes` (the slower of the
    /// two at peak), where the peaks are known.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bound_ms: Option<f64>,
    /// Which kernel the engine chose for the case, where it has several.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kernel: Option<String>,
}

/// A device's peak rates for one kind of work: floating-point operations and global-memory
/// bytes a second.
#[derive(Clone, Copy, Debug)]
pub struct Roof {
    pub flops_per_s: f64,
    pub bytes_per_s: f64,
}

impl Roof {
    /// The device's roof for f16 tensor-core work (`f16`) or f32 work, where its peaks are
    /// known ([`velox_engine::Caps::known_peaks`]).
    pub fn of(caps: &velox_engine::Caps, f16: bool) -> Option<Roof> {
        caps.known_peaks().map(|(tensor, fp32, gbps)| Roof {
            flops_per_s: if f16 { tensor } else { fp32 } * 1e12,
            bytes_per_s: gbps * 1e9,
        })
    }
}

impl Record {
    /// A timed case: `timing` as [`time_gpu`] returns it, and its rate in `unit`. The error is
    /// set with [`Record::against`] or [`Record::error`], the fraction of peak with
    /// [`Record::peak`].
    #[allow(clippy::too_many_arguments)]
    pub fn timed(
        name: impl Into<String>,
        shape: impl Into<String>,
        precision: impl Into<String>,
        device: &str,
        (median_ms, min_ms, gpu_timed): (f64, f64, bool),
        repeats: u32,
        throughput: f64,
        unit: &str,
    ) -> Record {
        Record {
            name: name.into(),
            shape: shape.into(),
            precision: precision.into(),
            device: device.into(),
            median_ms,
            min_ms,
            repeats,
            throughput,
            throughput_unit: unit.into(),
            peak_fraction: None,
            nmse: 0.0,
            max_abs_err: 0.0,
            error_over: "not measured".into(),
            gpu_timed,
            time_split_ms: None,
            dispatches_per_step: None,
            submits_per_step: None,
            peak_memory_bytes: None,
            family_ms: None,
            flops: None,
            bytes: None,
            bound_ms: None,
            kernel: None,
            step_ms_unoverlapped: None,
        }
    }

    /// The case's work: `flops` floating-point operations (0 for integer work) and `bytes` of
    /// compulsory global-memory traffic, and the roofline bound under `roof` where known.
    pub fn work(self, flops: f64, bytes: f64, roof: Option<Roof>) -> Record {
        let bound_ms = roof.map(|r| (flops / r.flops_per_s).max(bytes / r.bytes_per_s) * 1e3);
        Record { flops: Some(flops), bytes: Some(bytes), bound_ms, ..self }
    }

    /// The kernel the engine chose for the case.
    pub fn kernel(self, kernel: impl Into<String>) -> Record {
        Record { kernel: Some(kernel.into()), ..self }
    }

    pub fn peak(self, peak_fraction: Option<f64>) -> Record {
        Record { peak_fraction, ..self }
    }

    /// Error figures measured elsewhere, and what they were measured over.
    pub fn error(self, nmse: f64, max_abs_err: f64, over: impl Into<String>) -> Record {
        Record { nmse, max_abs_err, error_over: over.into(), ..self }
    }

    /// The error of `got` against the reference `want`.
    pub fn against<T: Copy + Into<f64>>(self, got: &[T], want: &[f64], over: impl Into<String>) -> Record {
        self.error(nmse(got, want), max_abs_err(got, want), over)
    }
}

pub fn write_json(path: &std::path::Path, records: &[Record]) -> CliResult<()> {
    velox_io::write_bytes(path, serde_json::to_string_pretty(records)?.as_bytes())?;
    println!("wrote {}", path.display());
    Ok(())
}

/// GPU times in ms of `repeats` runs of `f`, each in its own submission, after one warm-up run.
/// Returns (median, min, timed on the GPU).
pub fn time_gpu(
    gpu: &Gpu,
    repeats: u32,
    mut f: impl FnMut(&mut Recorder) -> Result<()>,
) -> Result<(f64, f64, bool)> {
    let mut times = Vec::with_capacity(repeats as usize);
    let mut gpu_timed = true;
    for i in 0..=repeats {
        let mut rec = gpu.recorder()?;
        let t0 = rec.timestamp();
        f(&mut rec)?;
        let t1 = rec.timestamp();
        let wall = std::time::Instant::now();
        let done = rec.submit()?;
        let ms = match (t0, t1) {
            (Some(a), Some(b)) => (done.timestamps_ns[b] - done.timestamps_ns[a]) / 1e6,
            _ => {
                gpu_timed = false;
                wall.elapsed().as_secs_f64() * 1e3
            }
        };
        if i > 0 {
            times.push(ms);
        }
    }
    times.sort_by(f64::total_cmp);
    Ok((times[times.len() / 2], times[0], gpu_timed))
}

pub fn print_header() {
    println!(
        "{:<26} {:<32} {:<9} {:>10} {:>18} {:>7} {:>10} {:>10} {:>8} {:>9}",
        "kernel",
        "shape",
        "precision",
        "median ms",
        "throughput",
        "% peak",
        "nmse",
        "max abs",
        "FLOP/B",
        "bound ms"
    );
}

/// PyTorch's median ms by (name, shape, precision), from `--peer`.
type PeerTimes = std::collections::BTreeMap<(String, String, String), f64>;
static PEER: std::sync::Mutex<Option<PeerTimes>> = std::sync::Mutex::new(None);

fn load_peer(path: Option<&std::path::Path>) -> CliResult<()> {
    let Some(path) = path else { return Ok(()) };
    let text = std::fs::read_to_string(path).map_err(|e| format!("--peer {}: {e}", path.display()))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format!("--peer {}: not JSON: {e}", path.display()))?;
    let records = json["records"].as_array().ok_or_else(|| {
        format!("--peer {}: no \"records\" list (the output of tools/peers/torch_bench.py)", path.display())
    })?;
    let s = |r: &serde_json::Value, k: &str| r[k].as_str().unwrap_or("").to_string();
    let map = records
        .iter()
        .filter_map(|r| Some(((s(r, "name"), s(r, "shape"), s(r, "precision")), r["median_ms"].as_f64()?)))
        .collect();
    *PEER.lock().unwrap_or_else(|e| e.into_inner()) = Some(map);
    Ok(())
}

/// Prints `r` as a row of the table (with PyTorch's time and the ratio under `--peer`) and keeps
/// it (see [`keep`]).
pub fn print_row(r: &Record) {
    keep(r);
    let peak = r.peak_fraction.map(|p| format!("{:.1}", 100.0 * p)).unwrap_or_else(|| "-".into());
    let peer = PEER.lock().unwrap_or_else(|e| e.into_inner()).as_ref().map(|m| {
        match m.get(&(r.name.clone(), r.shape.clone(), r.precision.clone())) {
            Some(&t) => format!("   PyTorch {t:.3} ms, ours x{:.2}", r.median_ms / t),
            None => "   PyTorch -".to_string(),
        }
    });
    println!(
        "{:<26} {:<32} {:<9} {:>10.3} {:>10} {:<7} {:>7} {:>10.2e} {:>10.2e} {:>8} {:>9}{}{}",
        r.name,
        r.shape,
        r.precision,
        r.median_ms,
        significant(r.throughput),
        r.throughput_unit,
        peak,
        r.nmse,
        r.max_abs_err,
        intensity(r),
        r.bound_ms.map(significant).unwrap_or_else(|| "-".into()),
        peer.unwrap_or_default(),
        r.kernel.as_ref().map(|k| format!("   [{k}]")).unwrap_or_default(),
    );
}

/// FLOPs per compulsory byte, "-" for integer work or where the record has no work figures.
fn intensity(r: &Record) -> String {
    match (r.flops, r.bytes) {
        (Some(f), Some(b)) if f > 0.0 && b > 0.0 => significant(f / b),
        _ => "-".into(),
    }
}

/// Four significant digits, without an exponent, for the magnitudes benchmarks produce.
fn significant(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let decimals = (3 - v.abs().log10().floor() as i32).clamp(0, 8) as usize;
    format!("{v:.decimals$}")
}
