//! Training and data from Python: `velox.train(kind, data, out, ...)` through the library's run
//! API (`velox_tasks::run`, as `velox train` does: the same run, step for step and bit for
//! bit, for the same settings on the same device), and `velox.data.synth(out, ...)`, the
//! scenes `velox data synth` writes.
//!
//! A run tells `progress(event)` what happens (a dict: `{"event": "note", "text"}`,
//! `{"event": "begin", "step", "steps"}`, `{"event": "step", "step", "steps", "loss",
//! "terms", "samples_per_second"}`, `{"event": "end", "completed"}`); `python/velox/__init__.py`
//! shows it with tqdm. Ctrl-C stops the run after the step under way, with its checkpoint
//! written, and raises `KeyboardInterrupt` naming it; an exception raised by `progress` stops
//! it the same way and is raised again.

use std::path::PathBuf;
use std::sync::Mutex;

use pyo3::exceptions::PyKeyboardInterrupt;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use velox_data::{procedural, SynthOptions};
use velox_models::config::GenerationTask;
use velox_models::run::{RunRequest, RunSettings};
use velox_models::train::collective::SingleProcess;
use velox_models::train::trainer::{Begin, Observer, Outcome, StepReport, Stop};
use velox_tasks::run::{RunSpec, TokenData};

use crate::device::{gpu_of, Device};
use crate::errors::{self, invalid};

/// What a run's observer and its stop share: the callback, and the first exception (the
/// callback's, or a pending Ctrl-C's) that stopped the run.
struct Shared {
    progress: Option<Py<PyAny>>,
    raised: Mutex<Option<PyErr>>,
}

impl Shared {
    /// Calls `progress` with the dict `event` builds; an exception stops the run.
    fn tell(&self, event: impl FnOnce(&Bound<'_, PyDict>) -> PyResult<()>) {
        let Some(progress) = &self.progress else { return };
        Python::attach(|py| {
            let told = (|| {
                let d = PyDict::new(py);
                event(&d)?;
                progress.call1(py, (d,)).map(|_| ())
            })();
            if let Err(e) = told {
                self.raised.lock().unwrap_or_else(|p| p.into_inner()).get_or_insert(e);
            }
        });
    }

    /// `result`, unless an exception stopped the work first: that exception then.
    fn finish<T>(&self, result: velox_data::DataResult<T>) -> PyResult<T> {
        match self.raised.lock().unwrap_or_else(|p| p.into_inner()).take() {
            Some(e) => Err(e),
            None => result.map_err(errors::data),
        }
    }

    /// Whether to stop: an exception came, or Ctrl-C (or another signal Python handles) is
    /// pending.
    fn stop(&self) -> bool {
        let mut raised = self.raised.lock().unwrap_or_else(|p| p.into_inner());
        if raised.is_none() {
            if let Err(e) = Python::attach(|py| py.check_signals()) {
                *raised = Some(e);
            }
        }
        raised.is_some()
    }
}

struct Events<'a>(&'a Shared);

impl Observer for Events<'_> {
    fn note(&mut self, text: &str) {
        self.0.tell(|d| {
            d.set_item("event", "note")?;
            d.set_item("text", text)
        });
    }

    fn begin(&mut self, settings: &RunSettings, start_step: u64) {
        self.0.tell(|d| {
            d.set_item("event", "begin")?;
            d.set_item("step", start_step)?;
            d.set_item("steps", settings.steps)
        });
    }

    fn step(&mut self, r: &StepReport, samples_per_second: f64) {
        self.0.tell(|d| {
            d.set_item("event", "step")?;
            d.set_item("step", r.step)?;
            d.set_item("loss", r.losses.total())?;
            let terms = PyDict::new(d.py());
            for (name, value) in r.losses.terms.iter().skip(1) {
                terms.set_item(name, value)?;
            }
            d.set_item("terms", terms)?;
            d.set_item("lr", r.lr)?;
            d.set_item("samples_per_second", samples_per_second)
        });
    }

    fn end(&mut self, completed: bool) {
        self.0.tell(|d| {
            d.set_item("event", "end")?;
            d.set_item("completed", completed)
        });
    }
}

fn precision_of(name: Option<&str>) -> PyResult<Option<velox_engine::Precision>> {
    match name {
        None => Ok(None),
        Some("f32") => Ok(Some(velox_engine::Precision::F32)),
        Some("f16") => Ok(Some(velox_engine::Precision::F16)),
        Some(other) => Err(invalid(format!("precision {other:?}: use \"f32\" or \"f16\""))),
    }
}

/// `velox.train(kind, data, out, ...)`: trains `kind` ("autoencoder", "voxels", "tracker" or
/// "generator") on the dataset `data` into the run folder `out`, as `velox train KIND` does
/// with the same settings; returns a dict of the outcome (`checkpoint`, `step`, `steps`,
/// `first_loss`, `last_loss`, `seconds`, `samples_per_second`, `stopped`).
#[pyfunction]
#[pyo3(signature = (kind, data, out, *, config = None, steps = None, seed = None, resume = false,
    init = None, steps_per_scene = None, accumulate = None, cooldown = None, precision = None,
    checkpoint_every = 200, plot_every = 25, stop_at = None, tokens = None, checkpoint = None,
    task = "video", dinov2 = None, progress = None, device = None, overlap = None))]
#[allow(clippy::too_many_arguments)]
fn train<'py>(
    py: Python<'py>,
    kind: &str,
    data: PathBuf,
    out: PathBuf,
    config: Option<String>,
    steps: Option<u64>,
    seed: Option<u64>,
    resume: bool,
    init: Option<PathBuf>,
    steps_per_scene: Option<u64>,
    accumulate: Option<u64>,
    cooldown: Option<u64>,
    precision: Option<&str>,
    checkpoint_every: u64,
    plot_every: u64,
    stop_at: Option<u64>,
    tokens: Option<PathBuf>,
    checkpoint: Option<PathBuf>,
    task: &str,
    dinov2: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
    device: Option<&Bound<'py, Device>>,
    overlap: Option<bool>,
) -> PyResult<Bound<'py, PyDict>> {
    let begin = match (init, resume) {
        (Some(_), true) => return Err(invalid("resume and init exclude each other: give one")),
        (Some(from), false) => Begin::Init(from),
        (None, true) => Begin::Resume,
        (None, false) => Begin::New,
    };
    for (name, v) in [
        ("steps", steps),
        ("steps_per_scene", steps_per_scene),
        ("accumulate", accumulate),
        ("stop_at", stop_at),
    ] {
        if v == Some(0) {
            return Err(invalid(format!("`{name}` must be at least 1")));
        }
    }
    let task = match task {
        "video" => GenerationTask::Video,
        "image" => GenerationTask::Image,
        other => return Err(invalid(format!("task {other:?}: use \"video\" or \"image\""))),
    };
    let spec = RunSpec {
        out,
        begin,
        config,
        request: RunRequest {
            seed,
            steps,
            steps_per_scene,
            cooldown,
            accumulate,
            precision: precision_of(precision)?,
        },
        checkpoint_every,
        plot_every,
        stop_at,
        overlap,
    };
    let token_data = TokenData { data: data.clone(), tokens, checkpoint };
    let gpu = gpu_of(py, device)?;
    let shared = Shared { progress, raised: Mutex::new(None) };
    let outcome = py.detach(|| -> velox_data::DataResult<Outcome> {
        let mut events = Events(&shared);
        let stop = || shared.stop();
        let c = &SingleProcess;
        match kind {
            "autoencoder" => velox_tasks::run::train_autoencoder(&gpu, &data, &spec, &mut events, &stop, c),
            "voxels" => velox_tasks::run::train_voxels(&gpu, &token_data, &spec, &mut events, &stop, c),
            "tracker" => velox_tasks::run::train_tracker(&gpu, &token_data, &spec, &mut events, &stop, c),
            "generator" => velox_tasks::run::train_generator(
                &gpu,
                &token_data,
                task,
                dinov2.as_deref(),
                &spec,
                &mut events,
                &stop,
                c,
            ),
            other => Err(velox_data::DataError::Invalid(format!(
                "kind {other:?}: use \"autoencoder\", \"voxels\", \"tracker\" or \"generator\""
            ))),
        }
    });
    let raised = shared.raised.lock().unwrap_or_else(|p| p.into_inner()).take();
    let o = match (outcome, raised) {
        (Ok(o), Some(e)) if o.stopped == Some(Stop::Asked) => {
            // The checkpoint holds the step the run stopped after: say so with the exception.
            if e.is_instance_of::<PyKeyboardInterrupt>(py) {
                return Err(PyKeyboardInterrupt::new_err(format!(
                    "stopped after step {} of {}; checkpoint {} holds it (continue with resume=True)",
                    o.last.step,
                    o.settings.steps,
                    o.checkpoint.display()
                )));
            }
            return Err(e);
        }
        (Err(_), Some(e)) => return Err(e),
        (Err(e), None) => return Err(errors::data(e)),
        (Ok(o), _) => o,
    };
    let d = PyDict::new(py);
    d.set_item("checkpoint", o.checkpoint.clone())?;
    d.set_item("step", o.last.step)?;
    d.set_item("steps", o.settings.steps)?;
    d.set_item("seed", o.settings.seed)?;
    d.set_item("precision", o.settings.precision.name())?;
    d.set_item("first_loss", o.first.losses.total())?;
    d.set_item("last_loss", o.last.losses.total())?;
    d.set_item("seconds", o.seconds)?;
    d.set_item("samples_per_second", o.samples_per_second)?;
    d.set_item("stopped", o.stopped.map(|s| if s == Stop::StopAt { "stop_at" } else { "asked" }))?;
    Ok(d)
}

/// The options of a dataset's scenes, checked.
fn synth_options(
    res: u32,
    points: usize,
    tracks: usize,
    supersample: u32,
    background: (f32, f32, f32),
) -> PyResult<SynthOptions> {
    let background = [background.0, background.1, background.2];
    let opts = SynthOptions { res, points, supersample, tracks, background };
    opts.check().map_err(errors::data)?;
    Ok(opts)
}

/// Writes the scene `name` of `mesh` into `out` as `velox data` does, telling `shared` of
/// each frame and of what the scene cannot serve.
#[allow(clippy::too_many_arguments)]
fn write_scene(
    gpu: &velox_engine::Gpu,
    shared: &Shared,
    out: &std::path::Path,
    name: &str,
    mesh: &velox_data::AnimatedMesh,
    source: &str,
    detail: Option<String>,
    seed: u64,
    opts: &SynthOptions,
) -> velox_data::DataResult<PathBuf> {
    let dir = out.join(name);
    let meta = velox_data::format::write_scene(gpu, mesh, source, detail, seed, opts, &dir, &mut |f| {
        shared.tell(|d| {
            d.set_item("event", "frame")?;
            d.set_item("scene", name)?;
            d.set_item("frame", f)?;
            d.set_item("frames", procedural::FRAMES)
        })
    })?;
    for (_, note) in velox_data::format::scene_notes(&meta, opts.tracks) {
        shared.tell(|d| {
            d.set_item("event", "note")?;
            d.set_item("text", format!("{name}: {note}"))
        });
    }
    Ok(dir)
}

fn create(out: &std::path::Path) -> velox_data::DataResult<()> {
    std::fs::create_dir_all(out)
        .map_err(|e| velox_data::DataError::Io(format!("cannot create {}: {e}", out.display())))
}

/// `velox.data.synth(out, scenes=8, seed=0, res=128, points=200000, tracks=1024,
/// supersample=2, background=(0, 0, 0))`: procedural scenes `scene_SSSSS` (seeds `seed` to `seed + scenes - 1`) in
/// `out`, as `velox data synth` writes them; returns their folders. `progress(event)` hears
/// `{"event": "frame", "scene", "frame", "frames"}` after each frame and `{"event": "note",
/// "text"}` for what a scene cannot serve.
#[pyfunction]
#[pyo3(signature = (out, *, scenes = 8, seed = 0, res = 128, points = 200_000, tracks = 1024, supersample = 2, background = (0.0, 0.0, 0.0), progress = None, device = None))]
#[allow(clippy::too_many_arguments)]
fn synth(
    py: Python<'_>,
    out: PathBuf,
    scenes: usize,
    seed: u64,
    res: u32,
    points: usize,
    tracks: usize,
    supersample: u32,
    background: (f32, f32, f32),
    progress: Option<Py<PyAny>>,
    device: Option<&Bound<'_, Device>>,
) -> PyResult<Vec<PathBuf>> {
    if scenes == 0 {
        return Err(invalid("`scenes` must be at least 1"));
    }
    let opts = synth_options(res, points, tracks, supersample, background)?;
    let gpu = gpu_of(py, device)?;
    let shared = Shared { progress, raised: Mutex::new(None) };
    let written = py.detach(|| -> velox_data::DataResult<Vec<PathBuf>> {
        create(&out)?;
        let mut dirs = Vec::new();
        for s in seed..seed + scenes as u64 {
            if shared.stop() {
                break;
            }
            let (recipe, mesh) = procedural::scene(s, None)?;
            let (source, detail) = (format!("procedural seed {s}"), Some(recipe.objects.join(", ")));
            dirs.push(write_scene(
                &gpu,
                &shared,
                &out,
                &format!("scene_{s:05}"),
                &mesh,
                &source,
                detail,
                s,
                &opts,
            )?);
        }
        Ok(dirs)
    });
    shared.finish(written)
}

/// `velox.data.gltf(files, out, animation=None, seed=0, res=128, points=200000, tracks=1024,
/// supersample=2, background=(0, 0, 0))`: a scene of each glTF 2.0 file (`.gltf` or `.glb`), `STEM_III`, in `out`,
/// as `velox data gltf` writes them (the scene of file i seeded with `seed + i`; a scene
/// already complete is kept). Returns a dict of `written`, `kept` (folders) and `failed`
/// (file -> reason): a file that cannot be imported does not stop the others.
#[pyfunction]
#[pyo3(signature = (files, out, *, animation = None, seed = 0, res = 128, points = 200_000, tracks = 1024, supersample = 2, background = (0.0, 0.0, 0.0), progress = None, device = None))]
#[allow(clippy::too_many_arguments)]
fn gltf<'py>(
    py: Python<'py>,
    files: Vec<PathBuf>,
    out: PathBuf,
    animation: Option<usize>,
    seed: u64,
    res: u32,
    points: usize,
    tracks: usize,
    supersample: u32,
    background: (f32, f32, f32),
    progress: Option<Py<PyAny>>,
    device: Option<&Bound<'py, Device>>,
) -> PyResult<Bound<'py, PyDict>> {
    if files.is_empty() {
        return Err(invalid("files: no glTF file given"));
    }
    let opts = synth_options(res, points, tracks, supersample, background)?;
    let gpu = gpu_of(py, device)?;
    let shared = Shared { progress, raised: Mutex::new(None) };
    type Outcome = (Vec<PathBuf>, Vec<PathBuf>, Vec<(String, String)>);
    let done = py.detach(|| -> velox_data::DataResult<Outcome> {
        create(&out)?;
        let (mut written, mut kept, mut failed) = (Vec::new(), Vec::new(), Vec::new());
        for (i, file) in files.iter().enumerate() {
            if shared.stop() {
                break;
            }
            let stem = file.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            let name = format!("{stem}_{i:03}");
            if out.join(&name).join("meta.json").is_file() {
                kept.push(out.join(&name));
                continue;
            }
            let source = file.display().to_string();
            let made = velox_data::gltf_import::import(file, animation).and_then(|imported| {
                for w in &imported.warnings {
                    shared.tell(|d| {
                        d.set_item("event", "note")?;
                        d.set_item("text", format!("{source}: {w}"))
                    });
                }
                let s = seed + i as u64;
                write_scene(&gpu, &shared, &out, &name, &imported.mesh, &source, imported.credits, s, &opts)
            });
            match made {
                Ok(dir) => written.push(dir),
                Err(e) => failed.push((source, e.to_string())),
            }
        }
        Ok((written, kept, failed))
    });
    let (written, kept, failed) = shared.finish(done)?;
    let d = PyDict::new(py);
    d.set_item("written", written)?;
    d.set_item("kept", kept)?;
    let reasons = PyDict::new(py);
    for (file, why) in failed {
        reasons.set_item(file, why)?;
    }
    d.set_item("failed", reasons)?;
    Ok(d)
}

/// `velox.data.import_rgbd(dir, out, depth_scale=0.001, max_depth=None, windows=None,
/// fps=None)`: an RGBD capture (`intrinsics.json`, `rgb/`, `depth/`) made into the tracker's
/// video folder `out` (or, with `windows=OVERLAP`, into windows of 24 consecutive frames), as
/// `velox import rgbd` makes it; returns what capture.json records (the videos and the frames
/// each took, the centre and the scale that map the box back to metres).
#[pyfunction]
#[pyo3(signature = (dir, out, *, depth_scale = 0.001, max_depth = None, windows = None, fps = None))]
fn import_rgbd<'py>(
    py: Python<'py>,
    dir: PathBuf,
    out: PathBuf,
    depth_scale: f64,
    max_depth: Option<f64>,
    windows: Option<usize>,
    fps: Option<f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let options = velox_data::capture::CaptureOptions { depth_scale, max_depth, windows, fps };
    let record =
        py.detach(|| velox_data::capture::import_rgbd(&dir, &out, &options)).map_err(errors::data)?;
    let text = serde_json::to_string(&record).map_err(|e| invalid(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(import_rgbd, m)?)?;
    m.add_function(wrap_pyfunction!(train, m)?)?;
    m.add_function(wrap_pyfunction!(synth, m)?)?;
    m.add_function(wrap_pyfunction!(gltf, m)?)?;
    Ok(())
}
