//! `velox._velox`: the extension module under the Python package `velox` (`python/velox/`),
//! over the library crates: numpy arrays in, numpy arrays out, library errors as Python
//! exceptions, the GIL released while the device works.
//!
//! - [`device`]: the devices and the default one every call takes unless given another;
//! - [`arrays`]: numpy arrays checked (dtype, shape, finite values) and read, never
//!   reinterpreted;
//! - [`gaussians`]: Gaussians as dicts of arrays, their PLY files and renders;
//! - [`models`]: the trained models (the autoencoder, the tracker);
//! - [`run`]: training through the library's run API (`velox_tasks::run`), and the data;
//! - [`metrics`]: the paper's metrics on arrays;
//! - [`view`]: the browser viewer of `velox view`;
//! - [`files`]: meshes, exports for other viewers, video files in.
//!
//! Tests: `python/tests/test_velox.py` (pytest, in a fresh venv: `tools/test.sh`).

use pyo3::prelude::*;

mod arrays;
mod device;
mod errors;
mod files;
mod gaussians;
mod metrics;
mod models;
mod run;
mod view;

#[pymodule]
fn _velox(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    device::register(m)?;
    gaussians::register(m)?;
    models::register(m)?;
    run::register(m)?;
    metrics::register(m)?;
    view::register(m)?;
    files::register(m)?;
    Ok(())
}
