//! `velox.devices()`, `velox.Device(name_or_index=None)`, and the default device: the one the
//! engine prefers (`VELOX_DEVICE` overrides, as for the command line), opened on first use and
//! shared by every call that is not given another.

use std::sync::Mutex;

use pyo3::prelude::*;
use pyo3::types::PyDict;
use velox_engine::Gpu;

use crate::errors;

/// A Vulkan device (`velox.Device`); every call that runs on a device takes one as `device=`.
#[pyclass(frozen, module = "velox", name = "Device")]
pub struct Device {
    pub gpu: Gpu,
}

static DEFAULT: Mutex<Option<Gpu>> = Mutex::new(None);

/// The default device, opened the first time it is asked for.
fn default_gpu(py: Python<'_>) -> PyResult<Gpu> {
    let mut slot = DEFAULT.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(gpu) = slot.as_ref() {
        return Ok(gpu.clone());
    }
    let gpu = py.detach(Gpu::new).map_err(errors::engine)?;
    *slot = Some(gpu.clone());
    Ok(gpu)
}

/// The device a call runs on: `device`, or the default one.
pub fn gpu_of(py: Python<'_>, device: Option<&Bound<'_, Device>>) -> PyResult<Gpu> {
    match device {
        Some(d) => Ok(d.get().gpu.clone()),
        None => default_gpu(py),
    }
}

#[pymethods]
impl Device {
    /// `Device()`: the default device; `Device(0)`: the device of that index in `devices()`;
    /// `Device("llvmpipe")`: the first whose name contains the text (case ignored).
    #[new]
    #[pyo3(signature = (name_or_index = None))]
    fn new(py: Python<'_>, name_or_index: Option<&Bound<'_, PyAny>>) -> PyResult<Device> {
        let Some(asked) = name_or_index else {
            return Ok(Device { gpu: default_gpu(py)? });
        };
        let name = if let Ok(i) = asked.extract::<usize>() {
            i.to_string()
        } else if let Ok(s) = asked.extract::<String>() {
            s
        } else {
            return Err(errors::invalid(format!(
                "name_or_index must be a device index or part of a name, got {}",
                asked.repr()?
            )));
        };
        let gpu = py.detach(|| Gpu::named(&name)).map_err(errors::engine)?;
        Ok(Device { gpu })
    }

    /// The device's name, as the driver gives it.
    #[getter]
    fn name(&self) -> String {
        self.gpu.caps().name.clone()
    }

    /// Whether it multiplies f16 on cooperative matrices (tensor cores): training then
    /// defaults to f16.
    #[getter]
    fn cooperative_matrix(&self) -> bool {
        velox_engine::ops::matmul::coop_kernel(self.gpu.caps()).is_some_and(|k| self.gpu.supports(k))
    }

    /// Bytes of device memory the engine holds now, and the most it has held.
    fn memory(&self) -> (u64, u64) {
        self.gpu.memory()
    }

    fn __repr__(&self) -> String {
        format!("velox.Device({:?})", self.gpu.caps().name)
    }
}

/// The Vulkan devices the loader sees: a dict each of `index`, `name`, `kind` (discrete,
/// integrated, virtual, cpu), `api_version` and `unusable` (why it cannot be used, or None).
#[pyfunction]
fn devices(py: Python<'_>) -> PyResult<Vec<Bound<'_, PyDict>>> {
    let list = py.detach(velox_engine::device::list_devices).map_err(errors::engine)?;
    list.into_iter()
        .map(|d| {
            let dict = PyDict::new(py);
            dict.set_item("index", d.index)?;
            dict.set_item("name", d.name)?;
            dict.set_item("kind", d.kind)?;
            dict.set_item("api_version", d.api_version)?;
            dict.set_item("unusable", d.unusable)?;
            Ok(dict)
        })
        .collect()
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Device>()?;
    m.add_function(wrap_pyfunction!(devices, m)?)?;
    Ok(())
}
