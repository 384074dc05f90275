//! Trained models from Python: `velox.Autoencoder.load(checkpoint)` with `encode`,
//! `decode_points` and `decode_gaussians`, loaded through the library's one way to load a
//! model (`velox_models::Model`), and decoding by the same rules as `velox decode`
//! (`velox_models::velox::decode`: the seed of a frame's noise, the voxels of its Gaussians).

use std::path::PathBuf;

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

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyAutoencoder>()?;
    Ok(())
}
