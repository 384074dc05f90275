//! `velox.view`: the viewer of `velox view` (`velox_tasks::view`) from Python: the one-file
//! page, or the page served from a thread of this process.

use std::path::PathBuf;

use pyo3::prelude::*;
use velox_tasks::view::{View, ViewOptions, ViewResult};

use crate::errors::{self, invalid};

/// A viewer error as the exception it is: a file's or the data's as theirs, else a
/// `ValueError` with the viewer's words.
fn error(e: Box<dyn std::error::Error + Send + Sync>) -> PyErr {
    let e = match e.downcast::<velox_engine::Error>() {
        Ok(engine) => return errors::engine(*engine),
        Err(e) => e,
    };
    match e.downcast::<velox_data::DataError>() {
        Ok(data) => errors::data(*data),
        Err(e) => invalid(e.to_string()),
    }
}

fn open(
    path: PathBuf,
    compare: Option<PathBuf>,
    scene: Option<PathBuf>,
    no_compare: bool,
) -> ViewResult<View> {
    if !path.exists() {
        return Err(Box::new(velox_engine::Error::file(
            &path,
            velox_engine::FileOp::Read,
            "no such file or folder",
        )));
    }
    View::open(&ViewOptions { path, scene, compare, no_compare })
}

/// The one-file page (manifest and frames inside) showing `path`, and its title.
#[pyfunction]
#[pyo3(signature = (path, *, compare = None, scene = None, no_compare = false))]
fn view_page(
    py: Python<'_>,
    path: PathBuf,
    compare: Option<PathBuf>,
    scene: Option<PathBuf>,
    no_compare: bool,
) -> PyResult<(String, String)> {
    py.detach(|| -> ViewResult<(String, String)> {
        let view = open(path, compare, scene, no_compare)?;
        Ok((view.page()?, view.title().to_string()))
    })
    .map_err(error)
}

/// Serves the page showing `path` on `host:port` (0: a free port) from a thread of this
/// process, for as long as it runs; returns the page's address and its title.
#[pyfunction]
#[pyo3(signature = (path, *, compare = None, scene = None, no_compare = false, host = "127.0.0.1", port = 0))]
fn view_serve(
    py: Python<'_>,
    path: PathBuf,
    compare: Option<PathBuf>,
    scene: Option<PathBuf>,
    no_compare: bool,
    host: &str,
    port: u16,
) -> PyResult<(String, String)> {
    let view = py.detach(|| open(path, compare, scene, no_compare)).map_err(error)?;
    let listener = std::net::TcpListener::bind((host, port))
        .map_err(|e| pyo3::exceptions::PyOSError::new_err(format!("cannot listen on {host}:{port}: {e}")))?;
    let bound = listener.local_addr().map_err(|e| pyo3::exceptions::PyOSError::new_err(e.to_string()))?;
    let title = view.title().to_string();
    std::thread::Builder::new()
        .name("velox-view".into())
        .spawn(move || view.serve(listener))
        .map_err(|e| pyo3::exceptions::PyRuntimeError::new_err(format!("cannot start the viewer: {e}")))?;
    Ok((format!("http://{bound}/"), title))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(view_page, m)?)?;
    m.add_function(wrap_pyfunction!(view_serve, m)?)?;
    Ok(())
}
