//! Library errors as Python exceptions: bad input (a value, a shape, a setting, a file's
//! content) is `ValueError`; a file that is not there `FileNotFoundError`, one that cannot be
//! read or written `OSError`, both with the path; the device's failures `RuntimeError`.
//! Settings are named as the keyword arguments that set them (`seed`, `stop_at`).

use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyRuntimeError, PyValueError};
use pyo3::PyErr;
use velox_data::DataError;
use velox_engine::{Error, FileOp};

/// `e` as the exception a Python caller expects.
pub fn engine(e: Error) -> PyErr {
    let message = e.to_string();
    match &e {
        Error::File { path, op: FileOp::Read, .. } if !path.exists() => {
            PyFileNotFoundError::new_err((2, message, path.display().to_string()))
        }
        Error::File { path, op: FileOp::Read | FileOp::Write, .. } => {
            PyOSError::new_err((5, message, path.display().to_string()))
        }
        Error::Io(_) => PyOSError::new_err(message),
        Error::File { op: FileOp::Content, .. }
        | Error::Invalid(_)
        | Error::Setting { .. }
        | Error::Shape(_)
        | Error::DType(_)
        | Error::TooLarge { .. } => PyValueError::new_err(message),
        Error::NoLoader(_)
        | Error::NoDevice(_)
        | Error::Vulkan { .. }
        | Error::OutOfMemory(_)
        | Error::Unsupported { .. }
        | Error::Mpi(_)
        | Error::Validation(_)
        | Error::Timeout { .. }
        | Error::DeviceLost(_) => PyRuntimeError::new_err(message),
    }
}

/// A data error as [`engine`] maps the engine's.
pub fn data(e: DataError) -> PyErr {
    match e {
        DataError::Engine(e) => engine(e),
        DataError::Io(m) => PyOSError::new_err(m),
        DataError::Invalid(m) => PyValueError::new_err(m),
    }
}

/// A `ValueError` saying `message`.
pub fn invalid(message: impl Into<String>) -> PyErr {
    PyValueError::new_err(message.into())
}
