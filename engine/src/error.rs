//! One error type for the engine: every failure names what went wrong and, where the user can
//! fix it, how.

use std::fmt;

use ash::vk;

#[derive(Debug)]
pub enum Error {
    /// The Vulkan loader library could not be opened.
    NoLoader(String),
    /// The loader works but no usable Vulkan 1.3 compute device was found.
    NoDevice(String),
    /// A Vulkan call failed.
    Vulkan { call: &'static str, result: vk::Result },
    /// Device memory could not be allocated.
    OutOfMemory(String),
    /// A tensor or dispatch exceeds what the device allows.
    TooLarge(String),
    /// Shapes, dtypes or arguments that do not fit the op.
    Shape(String),
    /// The device lacks something the request needs and there is no fallback.
    Unsupported(String),
    /// Bad input from outside (a file, an argument).
    Invalid(String),
    /// A file could not be written (a full disk, a file size limit, a missing folder); the
    /// message names the file.
    Io(String),
    /// A file that cannot be read, written or understood: its path, what was done with it and
    /// why it failed.
    File { path: std::path::PathBuf, op: FileOp, reason: String },
    /// A multi-process run over MPI failed or cannot start (an MPI call's error, ranks that
    /// disagree, a build without MPI started by mpirun); the message says which.
    Mpi(String),
    /// The Khronos validation layer (`VELOX_VALIDATE`) reported errors; the message gives the
    /// first new one with its VUID.
    Validation(String),
}

pub type Result<T> = std::result::Result<T, Error>;

/// What was done with a file that failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileOp {
    /// Opening or reading its bytes.
    Read,
    /// Writing it (atomically: the old file, if any, is left whole).
    Write,
    /// Reading what it says: its bytes are not what its format allows.
    Content,
}

impl Error {
    /// A file error: `path`, what was done with it and why it failed.
    pub fn file(path: &std::path::Path, op: FileOp, reason: impl fmt::Display) -> Error {
        Error::File { path: path.to_path_buf(), op, reason: reason.to_string() }
    }
}

/// What a machine without Vulkan needs, named once for every message that says so.
pub const INSTALL_HINT: &str = "install a Vulkan driver and loader: on Debian or Ubuntu \
`apt-get install libvulkan1 mesa-vulkan-drivers` (Mesa lavapipe runs on any CPU; Debian 12 users \
get a 3x faster one from bookworm-backports), or your GPU vendor's driver";

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::NoLoader(why) => {
                write!(f, "no Vulkan loader found ({why}); {INSTALL_HINT}")
            }
            Error::NoDevice(why) => write!(f, "no usable Vulkan device: {why}; {INSTALL_HINT}"),
            Error::Vulkan { call, result } => write!(f, "Vulkan call {call} failed: {result}"),
            Error::OutOfMemory(what) => write!(f, "out of device memory: {what}"),
            Error::TooLarge(what) => write!(f, "too large for this device: {what}"),
            Error::Shape(what) => write!(f, "shape error: {what}"),
            Error::Unsupported(what) => write!(f, "unsupported on this device: {what}"),
            Error::Invalid(what) => write!(f, "invalid input: {what}"),
            Error::Io(what) => write!(f, "{what}"),
            Error::File { path, op: FileOp::Read, reason } => {
                write!(f, "cannot read {}: {reason}", path.display())
            }
            Error::File { path, op: FileOp::Write, reason } => {
                write!(f, "cannot write {}: {reason}", path.display())
            }
            Error::File { path, op: FileOp::Content, reason } => write!(f, "{}: {reason}", path.display()),
            Error::Mpi(what) => write!(f, "MPI: {what}"),
            Error::Validation(what) => write!(f, "Vulkan validation: {what}"),
        }
    }
}

impl std::error::Error for Error {}

/// Attaches the name of the Vulkan call to its result code.
pub(crate) trait VkCheck<T> {
    fn vk(self, call: &'static str) -> Result<T>;
}

impl<T> VkCheck<T> for std::result::Result<T, vk::Result> {
    fn vk(self, call: &'static str) -> Result<T> {
        self.map_err(|result| match result {
            vk::Result::ERROR_OUT_OF_DEVICE_MEMORY | vk::Result::ERROR_OUT_OF_HOST_MEMORY => {
                Error::OutOfMemory(format!("{call} returned {result}"))
            }
            _ => Error::Vulkan { call, result },
        })
    }
}
