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
    /// A tensor or dispatch exceeds a limit of the device or of a kernel: which `limit`, and
    /// `what` went past it (with the sizes).
    TooLarge { limit: Limit, what: String },
    /// Shapes or arguments that do not fit the op (a tensor's shape and dtype checked together
    /// count here).
    Shape(String),
    /// A tensor of a dtype the op does not take, or operands whose dtypes differ.
    DType(String),
    /// The device lacks a `feature` the request needs and there is no fallback; `what` says
    /// what asked for it.
    Unsupported { feature: Feature, what: String },
    /// Bad input from outside (a file, an argument).
    Invalid(String),
    /// A setting a caller asked for that does not fit (a run's seed, its steps, where it
    /// starts from). `message` names each setting it speaks of as `{name}` (`{seed}`,
    /// `{stop_at}`), so that each front end spells it its own way ([`Error::spelled`]): the
    /// command line as `--seed`; `Display` (and Python) as `` `seed` ``. `setting` is the one
    /// at fault.
    Setting { setting: &'static str, message: String },
    /// A file could not be written (a full disk, a file size limit, a missing folder); the
    /// message names the file.
    Io(String),
    /// A file that cannot be read, written or understood: its path, what was done with it and
    /// why it failed.
    File { path: std::path::PathBuf, op: FileOp, reason: String },
    /// A multi-process run over MPI failed or cannot start (an MPI call's error, ranks that
    /// disagree, Open MPI's library missing under mpirun); the message says which.
    Mpi(String),
    /// The Khronos validation layer (`VELOX_VALIDATE`) reported errors; the message gives the
    /// first new one with its VUID.
    Validation(String),
    /// A submitted recording did not finish within the wait limit (`VELOX_WAIT_TIMEOUT`):
    /// which recording, and how long the host waited.
    Timeout { recording: String, waited: std::time::Duration },
    /// The driver reported the device lost (`VK_ERROR_DEVICE_LOST`: a kernel that faulted or
    /// ran past the driver's watchdog); nothing more can run on this device in this process.
    DeviceLost(String),
}

pub type Result<T> = std::result::Result<T, Error>;

/// The limit a [`Error::TooLarge`] request went past.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Limit {
    /// The largest buffer the device makes (`maxBufferSize`).
    Buffer,
    /// The largest storage buffer one binding reaches (`maxStorageBufferRange`).
    Binding,
    /// The workgroups of one dispatch (`maxComputeWorkGroupCount`).
    Workgroups,
    /// A count a kernel indexes with 32 bits (elements, words, items, ids), or a kernel's own
    /// bound below that.
    Index,
    /// A size past what host memory can address.
    Memory,
}

/// What a device lacks for an [`Error::Unsupported`] request.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Feature {
    /// f16 arithmetic and 16-bit storage in shaders.
    F16,
    /// f32 atomic add (`VK_EXT_shader_atomic_float`).
    FloatAtomics,
    /// f16 cooperative matrices (`VK_KHR_cooperative_matrix`).
    CooperativeMatrix,
    /// Subgroup arithmetic, vote and shuffle operations in compute shaders.
    Subgroups,
    /// The Vulkan memory model (`vulkanMemoryModel`).
    MemoryModel,
    /// Subgroups of one required size.
    SubgroupSize,
    /// Enough workgroup memory (`maxComputeSharedMemorySize`).
    WorkgroupMemory,
    /// Workgroups as large as a kernel's (`maxComputeWorkGroupInvocations`, `maxComputeWorkGroupSize`).
    WorkgroupSize,
    /// Room for a kernel's push constants (`maxPushConstantsSize`).
    PushConstants,
    /// Host-visible memory to stage transfers through.
    HostVisibleMemory,
    /// The Khronos validation layer (`VELOX_VALIDATE`).
    ValidationLayer,
    /// A kernel compiled for the request's sizes (attention's head widths).
    KernelVariant,
    /// Storage texel buffers of vec4s, or a view of a tensor as one (`maxTexelBufferElements`,
    /// `minTexelBufferOffsetAlignment`).
    TexelBuffers,
}

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
    /// A [`Error::TooLarge`] of `limit`.
    pub fn too_large(limit: Limit, what: impl fmt::Display) -> Error {
        Error::TooLarge { limit, what: what.to_string() }
    }

    /// An [`Error::Unsupported`] for the lack of `feature`.
    pub fn unsupported(feature: Feature, what: impl fmt::Display) -> Error {
        Error::Unsupported { feature, what: what.to_string() }
    }

    /// A [`Error::Setting`] about `setting`; `message` names settings as `{name}`.
    pub fn setting(setting: &'static str, message: impl fmt::Display) -> Error {
        Error::Setting { setting, message: message.to_string() }
    }

    /// The message with each setting `{name}` of an [`Error::Setting`] spelled by `spell`
    /// (`Display` spells it in backticks); any other error as `Display` shows it.
    pub fn spelled(&self, spell: impl Fn(&str) -> String) -> String {
        match self {
            Error::Setting { message, .. } => spell_settings(message, spell),
            other => other.to_string(),
        }
    }

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
            Error::TooLarge { what, .. } => write!(f, "too large for this device: {what}"),
            Error::Shape(what) => write!(f, "shape error: {what}"),
            Error::DType(what) => write!(f, "dtype error: {what}"),
            Error::Unsupported { what, .. } => write!(f, "unsupported on this device: {what}"),
            Error::Invalid(what) => write!(f, "invalid input: {what}"),
            Error::Setting { message, .. } => write!(f, "{}", spell_settings(message, |n| format!("`{n}`"))),
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
            Error::Timeout { recording, waited } => write!(
                f,
                "the device did not finish {recording} within {:.1} s (VELOX_WAIT_TIMEOUT sets the limit, in seconds)",
                waited.as_secs_f64()
            ),
            Error::DeviceLost(what) => write!(
                f,
                "the device was lost ({what}): a kernel faulted or ran past the driver's time limit; \
                 VELOX_VALIDATE=gpu or VELOX_ROBUST=1 may say which"
            ),
        }
    }
}

impl std::error::Error for Error {}

/// `message` with each `{name}` (lower-case letters, digits and `_`) replaced by `spell(name)`;
/// any other brace is kept.
fn spell_settings(message: &str, spell: impl Fn(&str) -> String) -> String {
    let mut out = String::with_capacity(message.len());
    let mut rest = message;
    while let Some(open) = rest.find('{') {
        out.push_str(&rest[..open]);
        let after = &rest[open + 1..];
        let name_len = after.find(|c: char| !(c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_'));
        match name_len {
            Some(n) if n > 0 && after[n..].starts_with('}') => {
                out.push_str(&spell(&after[..n]));
                rest = &after[n + 1..];
            }
            _ => {
                out.push('{');
                rest = after;
            }
        }
    }
    out.push_str(rest);
    out
}

/// `value` as a 32-bit count or index for a kernel, or a [`Limit::Index`] error naming `what`.
pub fn fit_u32<T: TryInto<u32> + Copy + fmt::Display>(
    value: T,
    what: impl FnOnce() -> String,
) -> Result<u32> {
    value.try_into().map_err(|_| {
        Error::too_large(Limit::Index, format!("{}: {value} is more than a 32-bit index holds", what()))
    })
}

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
            vk::Result::ERROR_DEVICE_LOST => Error::DeviceLost(format!("{call} returned {result}")),
            _ => Error::Vulkan { call, result },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_setting_error_is_spelled_by_its_front_end() {
        let e = Error::setting(
            "seed",
            "{seed} 2 differs from the 1 the run started with: leave {seed} out, or {out} {x",
        );
        assert_eq!(
            e.to_string(),
            "`seed` 2 differs from the 1 the run started with: leave `seed` out, or `out` {x"
        );
        let cli = e.spelled(|n| format!("--{}", n.replace('_', "-")));
        assert_eq!(cli, "--seed 2 differs from the 1 the run started with: leave --seed out, or --out {x");
        let stop = Error::setting("stop_at", "{stop_at} {} is not a step {Stop}");
        assert_eq!(stop.spelled(|n| format!("{n}=")), "stop_at= {} is not a step {Stop}");
        assert_eq!(Error::Invalid("x".into()).spelled(|_| unreachable!()), "invalid input: x");
    }
}
