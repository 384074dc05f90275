//! Trained models from Python: `velox.Autoencoder.load(checkpoint)` with `encode`,
//! `decode_points` and `decode_gaussians`, loaded through the library's one way to load a
//! model (`velox_models::Model`), and decoding by the same rules as `velox decode`
//! (`velox_models::velox::decode`: the seed of a frame's noise, the voxels of its Gaussians).

use std::path::PathBuf;

use numpy::PyArrayMethods;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use velox_engine::{Precision, Tensor};
use velox_models::velox::autoencoder::{frame_of_tau, tau_of, Autoencoder, FRAMES};
use velox_models::velox::decode::{frame_seed, Decoding, Sampling, VoxelSource};
use velox_models::velox::surface::{SampleSpec, Sampler};
use velox_models::Model;

use crate::arrays::{f32_array, to_array};
use crate::device::{gpu_of, Device};
use crate::errors::{self, invalid};
use crate::gaussians::to_dict;

/// A trained Velox autoencoder (`velox.Autoencoder`).
#[pyclass(frozen, module = "velox", name = "Autoencoder")]
pub struct PyAutoencoder {
    model: Autoencoder,
}

fn precision_of(name: &str) -> PyResult<Precision> {
    match name {
        "f32" => Ok(Precision::F32),
        "f16" => Ok(Precision::F16),
        other => Err(invalid(format!("precision {other:?}: use \"f32\" or \"f16\""))),
    }
}

fn sampler_of(name: &str) -> PyResult<Sampler> {
    match name {
        "heun" => Ok(Sampler::Heun),
        "euler" => Ok(Sampler::Euler),
        other => Err(invalid(format!("sampler {other:?}: use \"heun\" or \"euler\""))),
    }
}

fn frame_time(tau: f64) -> PyResult<f32> {
    if !(tau.is_finite() && (0.0..=1.0).contains(&tau)) {
        return Err(invalid(format!("tau {tau} must be a frame time in [0, 1] (frame f is f / 100)")));
    }
    Ok(tau as f32)
}

impl PyAutoencoder {
    /// `tokens` ([k, token_dim] float32) on the model's device.
    fn tokens(&self, tokens: &Bound<'_, PyAny>) -> PyResult<Tensor> {
        let d = self.model.cfg.encoder.token_dim;
        let (values, shape) = f32_array(tokens, "tokens", &[None, Some(d)])?;
        if shape[0] == 0 {
            return Err(invalid(format!("tokens must hold at least one token, got shape {shape:?}")));
        }
        Tensor::from_slice(self.model.store.flat_params().gpu(), &shape, &values).map_err(errors::engine)
    }

    /// The sampling of the surface at `tau`: the noise of frame `round(100 tau)` of a decoding
    /// seeded with `seed`, as `velox decode` draws it.
    fn spec(&self, tau: f32, points: usize, steps: usize, sampler: &str, seed: u64) -> PyResult<SampleSpec> {
        if points == 0 || steps == 0 {
            return Err(invalid(format!("n ({points}) and steps ({steps}) must be positive")));
        }
        Ok(SampleSpec {
            points,
            steps,
            sampler: sampler_of(sampler)?,
            seed: frame_seed(seed, frame_of_tau(tau)),
            precision: self.model.precision(),
        })
    }
}

#[pymethods]
impl PyAutoencoder {
    /// `Autoencoder.load(checkpoint, precision="f32", device=None)`: the autoencoder a
    /// checkpoint (or weights file) of `velox train autoencoder` holds.
    #[staticmethod]
    #[pyo3(signature = (checkpoint, *, precision = "f32", device = None))]
    fn load(
        py: Python<'_>,
        checkpoint: PathBuf,
        precision: &str,
        device: Option<&Bound<'_, Device>>,
    ) -> PyResult<PyAutoencoder> {
        let precision = precision_of(precision)?;
        let gpu = gpu_of(py, device)?;
        let model = py
            .detach(|| -> velox_engine::Result<Autoencoder> {
                let mut model = Autoencoder::load(&gpu, &checkpoint)?;
                model.set_precision(precision)?;
                Ok(model)
            })
            .map_err(errors::engine)?;
        Ok(PyAutoencoder { model })
    }

    /// The config's name (`"small"`, ...).
    #[getter]
    fn config(&self) -> String {
        self.model.config_name().to_string()
    }

    /// The config as a dict (the JSON a checkpoint stores).
    fn config_dict<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let text = serde_json::to_string(&self.model.cfg).map_err(|e| invalid(e.to_string()))?;
        py.import("json")?.call_method1("loads", (text,))
    }

    /// Tokens per cloud (k) and their width.
    #[getter]
    fn token_shape(&self) -> (usize, usize) {
        (self.model.cfg.encoder.tokens, self.model.cfg.encoder.token_dim)
    }

    /// `encode(cloud, seed=0)`: the dynamic tokens [k, token_dim] of a 4D colour point cloud,
    /// float32 [N, 7] rows of x, y, z (in [-1, 1]), r, g, b (in [0, 1]), tau (frame / 100), the
    /// encoder's queries drawn from `seed`: the tokens `velox decode --seed` decodes.
    #[pyo3(signature = (cloud, *, seed = 0))]
    fn encode<'py>(
        &self,
        py: Python<'py>,
        cloud: &Bound<'py, PyAny>,
        seed: u64,
    ) -> PyResult<Bound<'py, PyAny>> {
        let (rows, _) = f32_array(cloud, "cloud", &[None, Some(7)])?;
        let tokens = py
            .detach(|| -> velox_engine::Result<Vec<f32>> {
                Decoding::encode(&self.model, &rows, seed)?.tokens().read()
            })
            .map_err(errors::engine)?;
        let (k, d) = self.token_shape();
        to_array(py, tokens, &[k, d])
    }

    /// `decode_points(tokens, tau, n, steps=20, sampler="heun", seed=0)`: n surface points
    /// [n, 3] at frame time tau, sampled by the 4D surface decoder's flow; at a frame's time
    /// with a frame's seed, the points `velox decode points` writes.
    #[pyo3(signature = (tokens, tau, n, *, steps = 20, sampler = "heun", seed = 0))]
    #[allow(clippy::too_many_arguments)]
    fn decode_points<'py>(
        &self,
        py: Python<'py>,
        tokens: &Bound<'py, PyAny>,
        tau: f64,
        n: usize,
        steps: usize,
        sampler: &str,
        seed: u64,
    ) -> PyResult<Bound<'py, PyAny>> {
        let tau = frame_time(tau)?;
        let spec = self.spec(tau, n, steps, sampler, seed)?;
        let tokens = self.tokens(tokens)?;
        let xyz =
            py.detach(|| self.model.decode_points(&tokens, tau, &spec)?.read()).map_err(errors::engine)?;
        to_array(py, xyz, &[n, 3])
    }

    /// `decode_gaussians(tokens, tau, cloud=None, points=16384, steps=20, sampler="heun",
    /// seed=0, raw=False)`: the Gaussians of the frame at time tau (f / 100), as a dict
    /// (`velox.read_gaussians`' layout). Their queries are the occupied voxels of the input
    /// cloud's points of that frame when `cloud` is given (as in training), else of `points`
    /// surface points sampled from the tokens: what `velox decode gaussians --voxels
    /// cloud|surface` writes for that frame.
    #[pyo3(signature = (tokens, tau, *, cloud = None, points = 16384, steps = 20, sampler = "heun", seed = 0, raw = false))]
    #[allow(clippy::too_many_arguments)]
    fn decode_gaussians<'py>(
        &self,
        py: Python<'py>,
        tokens: &Bound<'py, PyAny>,
        tau: f64,
        cloud: Option<&Bound<'py, PyAny>>,
        points: usize,
        steps: usize,
        sampler: &str,
        seed: u64,
        raw: bool,
    ) -> PyResult<Bound<'py, PyDict>> {
        let frame = frame_of_tau(frame_time(tau)?);
        if frame >= FRAMES || (tau_of(frame) as f64 - tau).abs() > 1e-6 {
            return Err(invalid(format!(
                "tau {tau} is not a frame's time: the Gaussians decode at f / 100 for a frame f of 0 to {}",
                FRAMES - 1
            )));
        }
        if points == 0 || steps == 0 {
            return Err(invalid(format!("points ({points}) and steps ({steps}) must be positive")));
        }
        let sampling = Sampling { points, steps, sampler: sampler_of(sampler)? };
        let tokens = self.tokens(tokens)?;
        let cloud = cloud.map(|c| f32_array(c, "cloud", &[None, Some(7)]).map(|(v, _)| v)).transpose()?;
        let source = if cloud.is_some() { VoxelSource::Input } else { VoxelSource::Surface };
        let g = py
            .detach(|| -> velox_engine::Result<_> {
                let decoding = Decoding::from_tokens(&self.model, tokens, cloud.as_deref(), seed)?;
                let centres = decoding.voxels(frame, source, &sampling)?;
                decoding.gaussians(frame, &centres)?.try_map(|t, _| t.read::<f32>())
            })
            .map_err(errors::engine)?;
        to_dict(py, g, raw)
    }

    fn __repr__(&self) -> String {
        let (k, d) = self.token_shape();
        format!("velox.Autoencoder(config={:?}, tokens=[{k}, {d}])", self.model.config_name())
    }
}

/// A trained 3D tracker (`velox.Tracker`), with the autoencoder whose tokens it learned.
#[pyclass(frozen, module = "velox", name = "Tracker")]
pub struct PyTracker {
    tracker: velox_models::velox::tracker::Tracker,
    autoencoder: Autoencoder,
}

/// An RGBD video from Python: a folder (a dataset scene, or `fFF.png`, `fFF_depth.exr` and
/// `camera.json`), or a dict of `rgb` [24, H, W, 3] and `depth` [24, H, W] (camera-space z, 0
/// where nothing is) float32 arrays and `camera` (as `velox.render` takes it).
fn video_of(video: &Bound<'_, PyAny>) -> PyResult<velox_data::rgbd::RgbdVideo> {
    if let Ok(path) = video.extract::<PathBuf>() {
        return velox_tasks::track::read_video(&path).map_err(errors::data);
    }
    let d = video.cast::<PyDict>().map_err(|_| {
        invalid("video must be a folder, or a dict of rgb [24, H, W, 3], depth [24, H, W] and camera")
    })?;
    let item = |key: &str| -> PyResult<Bound<'_, PyAny>> {
        d.get_item(key)?.ok_or_else(|| invalid(format!("video has no {key:?}")))
    };
    let (rgb, shape) = f32_array(&item("rgb")?, "video[\"rgb\"]", &[Some(FRAMES), None, None, Some(3)])?;
    let (h, w) = (shape[1], shape[2]);
    let (depth, _) = f32_array(&item("depth")?, "video[\"depth\"]", &[Some(FRAMES), Some(h), Some(w)])?;
    if let Some(z) = depth.iter().find(|&&z| z < 0.0) {
        return Err(invalid(format!("video[\"depth\"] holds {z}: depths are 0 (no surface) or positive")));
    }
    let camera = crate::gaussians::camera_of(&item("camera")?, w as u32, h as u32)?;
    Ok(velox_data::rgbd::RgbdVideo {
        camera,
        rgb: rgb.chunks(h * w * 3).map(<[f32]>::to_vec).collect(),
        depth: depth.chunks(h * w).map(<[f32]>::to_vec).collect(),
    })
}

#[pymethods]
impl PyTracker {
    /// `Tracker.load(checkpoint, autoencoder, device=None)`: a tracker of `velox train
    /// tracker`, and the autoencoder checkpoint whose encoder made the tokens it learned
    /// (checked).
    #[staticmethod]
    #[pyo3(signature = (checkpoint, autoencoder, *, device = None))]
    fn load(
        py: Python<'_>,
        checkpoint: PathBuf,
        autoencoder: PathBuf,
        device: Option<&Bound<'_, Device>>,
    ) -> PyResult<PyTracker> {
        let gpu = gpu_of(py, device)?;
        py.detach(|| -> velox_engine::Result<PyTracker> {
            let tracker = velox_models::velox::tracker::Tracker::load(&gpu, &checkpoint)?;
            tracker.check_encoder(&autoencoder)?;
            Ok(PyTracker { tracker, autoencoder: Autoencoder::load(&gpu, &autoencoder)? })
        })
        .map_err(errors::engine)
    }

    /// `track(video, queries=None, grid=16, points=100000, seed=0)`: each query point [Q, 3]
    /// on the first frame (default: the pixels of a grid x grid lattice of the first frame
    /// that show surface, back-projected) followed through the video's 24 frames: a dict of
    /// `queries` [Q, 3], `tracks` [Q, 24, 3] and `visible` [Q, 24] (bool: the video shows the
    /// point there), and `frames` (the capture's frame of each). A capture imported with
    /// `windows` (`velox import rgbd --windows`) is tracked over all its frames, each window
    /// from where the one before puts the queries. Each video back-projects to at most
    /// `points` points, drawn with `seed`: what `velox track` writes to tracks.json.
    #[pyo3(signature = (video, *, queries = None, grid = 16, points = velox_data::rgbd::DEFAULT_POINTS, seed = 0))]
    fn track<'py>(
        &self,
        py: Python<'py>,
        video: &Bound<'py, PyAny>,
        queries: Option<&Bound<'py, PyAny>>,
        grid: usize,
        points: usize,
        seed: u64,
    ) -> PyResult<Bound<'py, PyDict>> {
        if grid == 0 || points == 0 {
            return Err(invalid(format!("grid ({grid}) and points ({points}) must be positive")));
        }
        // A capture imported in windows is tracked as one clip over all its frames.
        let windows = match video.extract::<PathBuf>() {
            Ok(dir) => velox_tasks::track::read_windows(&dir).map_err(errors::data)?,
            Err(_) => None,
        };
        let first = match &windows {
            Some(w) => w[0].0.clone(),
            None => video_of(video)?,
        };
        let queries: Vec<[f32; 3]> = match queries {
            Some(q) => {
                let (v, _) = f32_array(q, "queries", &[None, Some(3)])?;
                v.chunks(3).map(|p| [p[0], p[1], p[2]]).collect()
            }
            None => velox_tasks::track::grid_queries(&first, grid),
        };
        if queries.is_empty() {
            return Err(invalid(format!(
                "no pixel of a {grid} x {grid} grid on the first frame shows surface: give queries or a finer grid"
            )));
        }
        let (ae, tracker) = (&self.autoencoder, &self.tracker);
        let stitched = py
            .detach(|| match &windows {
                Some(w) => velox_tasks::track::track_windows(ae, tracker, w, &queries, points, seed),
                None => velox_tasks::track::track(ae, tracker, &first, &queries, points, seed).map(|t| {
                    velox_tasks::track::StitchedTracks {
                        frames: (0..FRAMES).collect(),
                        tracks: t.tracks.iter().map(|x| x.to_vec()).collect(),
                        visible: t.visible.iter().map(|x| x.to_vec()).collect(),
                    }
                }),
            })
            .map_err(errors::data)?;
        let (q, f) = (queries.len(), stitched.frames.len());
        let d = PyDict::new(py);
        d.set_item("queries", to_array(py, queries.into_iter().flatten().collect(), &[q, 3])?)?;
        d.set_item("frames", stitched.frames)?;
        let xyz: Vec<f32> = stitched.tracks.iter().flatten().flatten().copied().collect();
        d.set_item("tracks", to_array(py, xyz, &[q, f, 3])?)?;
        let visible: Vec<bool> = stitched.visible.iter().flatten().copied().collect();
        d.set_item("visible", numpy::PyArray1::from_vec(py, visible).reshape([q, f])?)?;
        Ok(d)
    }

    fn __repr__(&self) -> String {
        format!("velox.Tracker(config={:?})", self.tracker.config_name())
    }
}

/// A trained generator (`velox.Generator`, video-to-4D or image-to-4D), with the autoencoder
/// whose tokens it makes and DINOv2 where it reads its features, checked against it.
#[pyclass(frozen, module = "velox", name = "Generator")]
pub struct PyGenerator {
    models: velox_tasks::generate::GeneratorModels,
}

#[pymethods]
impl PyGenerator {
    /// `Generator.load(checkpoint, autoencoder, dinov2=None, device=None)`: a generator of
    /// `velox train generator`, the autoencoder checkpoint it was trained against, and the
    /// DINOv2 weights when it reads DINOv2's features.
    #[staticmethod]
    #[pyo3(signature = (checkpoint, autoencoder, *, dinov2 = None, device = None))]
    fn load(
        py: Python<'_>,
        checkpoint: PathBuf,
        autoencoder: PathBuf,
        dinov2: Option<PathBuf>,
        device: Option<&Bound<'_, Device>>,
    ) -> PyResult<PyGenerator> {
        let gpu = gpu_of(py, device)?;
        let models = py
            .detach(|| {
                velox_tasks::generate::GeneratorModels::load(
                    &gpu,
                    &checkpoint,
                    &autoencoder,
                    dinov2.as_deref(),
                )
            })
            .map_err(errors::engine)?;
        Ok(PyGenerator { models })
    }

    /// "video" or "image": what the generator is conditioned on.
    #[getter]
    fn task(&self) -> &'static str {
        match self.models.generator.cfg.task {
            velox_models::config::GenerationTask::Video => "video",
            velox_models::config::GenerationTask::Image => "image",
        }
    }

    /// `generate(condition, steps=20, sampler="euler", guidance=3.0, seed=0)`: the tokens
    /// [k, token_dim] of the object the condition shows, in the autoencoder's space (decode
    /// them with `velox.Autoencoder`): what `velox generate` stores in tokens.safetensors.
    /// `condition` is a video folder (a dataset scene, or PNG frames), an image file (the image
    /// task), or float32 frames [T, H, W, 3] in [0, 1] (the video task reads 24 of them,
    /// spread evenly; the image task the first), each cropped square and resized as the files
    /// are (after rounding to 8 bits, as a PNG holds them).
    #[pyo3(signature = (condition, *, steps = 20, sampler = "euler", guidance = 3.0, seed = 0))]
    fn generate<'py>(
        &self,
        py: Python<'py>,
        condition: &Bound<'py, PyAny>,
        steps: usize,
        sampler: &str,
        guidance: f32,
        seed: u64,
    ) -> PyResult<Bound<'py, PyAny>> {
        let cfg = &self.models.generator.cfg;
        if steps == 0 || !guidance.is_finite() {
            return Err(invalid(format!(
                "steps ({steps}) must be positive and guidance ({guidance}) finite"
            )));
        }
        let size = cfg.image_size;
        let pixels = if let Ok(path) = condition.extract::<PathBuf>() {
            velox_tasks::condition::read_condition(&path, cfg.task, size).map_err(errors::data)?
        } else {
            let (values, shape) = f32_array(condition, "condition", &[None, None, None, Some(3)])?;
            let (t, h, w) = (shape[0], shape[1], shape[2]);
            let frames = cfg.task.frames();
            if t < frames || h == 0 || w == 0 {
                return Err(invalid(format!(
                    "condition has shape {shape:?}: this generator reads {frames} frame(s) of [H, W, 3]"
                )));
            }
            let mut pixels = Vec::with_capacity(frames * 3 * size * size);
            for i in velox_tasks::condition::spread(t, frames) {
                let frame = &values[i * h * w * 3..(i + 1) * h * w * 3];
                let bytes = frame.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
                let img = image_of(w as u32, h as u32, bytes);
                pixels.extend(velox_tasks::condition::condition_frame(&img, size).map_err(errors::data)?);
            }
            pixels
        };
        let spec = velox_models::velox::generator::GenerateSpec {
            steps,
            sampler: sampler_of(sampler)?,
            guidance,
            seed,
            precision: Precision::F32,
        };
        let m = &self.models;
        let gpu = m.ae.store.flat_params().gpu().clone();
        let (tokens, shape) = py
            .detach(|| -> velox_engine::Result<_> {
                let t = m.generate(&gpu, &pixels, &spec, &mut |_| {})?;
                Ok((t.read::<f32>()?, t.shape().to_vec()))
            })
            .map_err(errors::engine)?;
        to_array(py, tokens, &shape)
    }

    fn __repr__(&self) -> String {
        format!("velox.Generator(config={:?}, task={:?})", self.models.generator.config_name(), self.task())
    }
}

/// An RGB image of 8-bit rows.
fn image_of(w: u32, h: u32, bytes: Vec<u8>) -> velox_tasks::condition::RgbImage {
    velox_tasks::condition::RgbImage::from_raw(w, h, bytes).expect("w * h * 3 bytes")
}

/// `velox.encode_dataset(checkpoint, data, out=None, source="points", seed=0,
/// precision="f32", force=False, video_points=100000)`: the tokens of every scene of a
/// dataset stored beside it (DATA/tokens; with `source="video"`, of the scenes' RGBD videos,
/// DATA/tokens-video) for the models that train on them, as `velox encode` stores them.
/// Returns a dict of `dir`, `encoded` and `kept` (scene names).
#[pyfunction]
#[pyo3(signature = (checkpoint, data, *, out = None, source = "points", seed = 0, precision = "f32", force = false, video_points = velox_data::rgbd::DEFAULT_POINTS, device = None))]
#[allow(clippy::too_many_arguments)]
fn encode_dataset<'py>(
    py: Python<'py>,
    checkpoint: PathBuf,
    data: PathBuf,
    out: Option<PathBuf>,
    source: &str,
    seed: u64,
    precision: &str,
    force: bool,
    video_points: usize,
    device: Option<&Bound<'py, Device>>,
) -> PyResult<Bound<'py, PyDict>> {
    use velox_models::velox::tokens::CloudSource;
    let source = match source {
        "points" => CloudSource::Points,
        "video" => CloudSource::Video,
        other => return Err(invalid(format!("source {other:?}: use \"points\" or \"video\""))),
    };
    if video_points == 0 {
        return Err(invalid("`video_points` must be at least 1"));
    }
    let options = velox_tasks::encode::EncodeOptions {
        checkpoint,
        data,
        out,
        seed,
        precision: precision_of(precision)?,
        force,
        source,
        video_points,
    };
    let gpu = gpu_of(py, device)?;
    let report =
        py.detach(|| velox_tasks::encode::encode_dataset(&gpu, &options, &mut ())).map_err(errors::data)?;
    let d = PyDict::new(py);
    d.set_item("dir", report.dir)?;
    d.set_item("encoded", report.encoded)?;
    d.set_item("kept", report.kept)?;
    Ok(d)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyAutoencoder>()?;
    m.add_class::<PyTracker>()?;
    m.add_class::<PyGenerator>()?;
    m.add_function(wrap_pyfunction!(encode_dataset, m)?)?;
    Ok(())
}
