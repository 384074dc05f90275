//! The Khronos validation layer, under `VELOX_VALIDATE`, with every error counted.
//!
//! `VELOX_VALIDATE=1` loads `VK_LAYER_KHRONOS_validation` with synchronization validation on;
//! `VELOX_VALIDATE=gpu` loads it with GPU-assisted validation instead (shaders instrumented to
//! report reads and writes past a binding; slower per kernel, so meant for the op-level tests).
//! Further settings come from the layer's own `vk_layer_settings.txt` (the project keeps one at
//! its root; `VK_LAYER_SETTINGS_PATH` points the layer at it). A device opened under validation
//! binds buffers through descriptor sets, not push descriptors: the layer's synchronization
//! checks do not track accesses made through push descriptors.
//!
//! A debug messenger counts every message of error severity, prints its VUID and text, and keeps
//! the first few, for the process and for the thread whose Vulkan call the layer reported it in
//! (the layer calls the messenger on that thread: recording, pipeline creation and submit
//! checks arrive on the thread that records and submits). [`Recorder::submit`](crate::Recorder::submit)
//! fails with [`Error::Validation`], naming the recording, when errors arrived on its thread since
//! that thread last reported one, so the test that fails is the one whose work the layer
//! reported, even while tests share one device on parallel threads. The `velox` command exits
//! non-zero when the process's count is above zero at its end ([`error_count`]), and the test
//! binaries' shared device does the same at exit for errors no submit reported. Asking for
//! validation where the layer is not installed is an error, not a silent run without it.

use std::ffi::{c_void, CStr};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use ash::vk;

use crate::error::{Error, Result, VkCheck};

/// What `VELOX_VALIDATE` asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// No layer (unset, empty or `0`).
    Off,
    /// Core checks and synchronization validation (`1`, `sync`).
    Sync,
    /// Core checks and GPU-assisted validation (`gpu`).
    GpuAssisted,
}

impl Mode {
    /// The mode `VELOX_VALIDATE` names; an unknown value is an error that lists the known ones.
    pub fn from_env() -> Result<Mode> {
        match std::env::var("VELOX_VALIDATE").as_deref().map(str::trim) {
            Err(_) | Ok("") | Ok("0") => Ok(Mode::Off),
            Ok("1") | Ok("sync") => Ok(Mode::Sync),
            Ok("gpu") => Ok(Mode::GpuAssisted),
            Ok(other) => Err(Error::Invalid(format!(
                "VELOX_VALIDATE={other}: use 1 (or sync) for core and synchronization checks, gpu for \
                 GPU-assisted validation, 0 for none"
            ))),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Mode::Off => "off",
            Mode::Sync => "core + synchronization",
            Mode::GpuAssisted => "core + GPU-assisted",
        }
    }

    /// The layer's optional checks this mode turns on.
    pub(crate) fn features(self) -> &'static [vk::ValidationFeatureEnableEXT] {
        match self {
            Mode::Off => &[],
            Mode::Sync => &[vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION],
            Mode::GpuAssisted => &[vk::ValidationFeatureEnableEXT::GPU_ASSISTED],
        }
    }
}

pub(crate) const LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";

/// Messages of error severity since the process started, and how many of them a check has
/// reported (on the thread they arrived on).
static ERRORS: AtomicUsize = AtomicUsize::new(0);
static REPORTED: AtomicUsize = AtomicUsize::new(0);
/// The first [`KEPT`] of them, as printed.
static FIRST: Mutex<Vec<String>> = Mutex::new(Vec::new());
const KEPT: usize = 16;

/// This thread's errors: how many, how many of them a check has reported, and the first few.
#[derive(Default)]
struct ThreadErrors {
    count: usize,
    reported: usize,
    first: Vec<String>,
}

thread_local! {
    static THREAD: std::cell::RefCell<ThreadErrors> = std::cell::RefCell::new(ThreadErrors::default());
}

/// Errors whose message names a command buffer (GPU-assisted checks report them from the
/// layer's own threads), by its handle: they belong to the recording of that command buffer.
static BY_COMMAND_BUFFER: Mutex<Vec<(u64, Vec<String>)>> = Mutex::new(Vec::new());

/// Validation errors reported since the process started (0 when validation is off).
pub fn error_count() -> usize {
    ERRORS.load(Ordering::Acquire)
}

/// Validation errors no check reported on the thread they arrived on: made by work that never
/// submitted after them. The `velox` command and the test binaries fail on them at exit.
pub fn unreported_count() -> usize {
    error_count().saturating_sub(REPORTED.load(Ordering::Acquire))
}

/// Validation errors the layer reported on this thread's Vulkan calls since it started.
pub fn thread_error_count() -> usize {
    THREAD.with(|t| t.borrow().count)
}

/// The errors that no check has reported yet of the recording whose command buffer is `cmd`
/// (those naming it, wherever they arrived) and of this thread (those naming no command buffer):
/// marks them reported and returns the error naming the first, with `what` the work they
/// arrived during.
pub(crate) fn take_failure(cmd: Option<u64>, what: &str) -> Option<Error> {
    let mut new: Vec<String> = Vec::new();
    if let Some(cmd) = cmd {
        if let Ok(mut by) = BY_COMMAND_BUFFER.lock() {
            if let Some(i) = by.iter().position(|(h, _)| *h == cmd) {
                new.extend(by.swap_remove(i).1);
            }
        }
    }
    let thread_new = THREAD.with(|t| {
        let mut t = t.borrow_mut();
        let n = t.count - t.reported;
        let first = t.first.get(t.reported).or(t.first.last()).cloned();
        t.reported = t.count;
        (n, first)
    });
    let count = new.len() + thread_new.0;
    if count == 0 {
        return None;
    }
    REPORTED.fetch_add(count, Ordering::AcqRel);
    let shown = new.first().cloned().or(thread_new.1).unwrap_or_default();
    Some(Error::Validation(format!(
        "{count} new validation error(s) during {what} ({} in the process); first new one: {shown}",
        error_count()
    )))
}

/// Forgets what was kept for the command buffer `cmd` (its recording is gone; the handle may
/// be reused). Errors still unreported stay counted by [`unreported_count`].
pub(crate) fn forget_command_buffer(cmd: u64) {
    if let Ok(mut by) = BY_COMMAND_BUFFER.lock() {
        by.retain(|(h, _)| *h != cmd);
    }
}

/// The first validation errors reported in the process, each as `VUID: message`.
pub fn first_errors() -> Vec<String> {
    FIRST.lock().map(|v| v.clone()).unwrap_or_default()
}

/// The messenger's create info: errors and warnings, of every type.
pub(crate) fn messenger_info() -> vk::DebugUtilsMessengerCreateInfoEXT<'static> {
    vk::DebugUtilsMessengerCreateInfoEXT::default()
        .message_severity(
            vk::DebugUtilsMessageSeverityFlagsEXT::ERROR | vk::DebugUtilsMessageSeverityFlagsEXT::WARNING,
        )
        .message_type(
            vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
                | vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
        )
        .pfn_user_callback(Some(callback))
}

/// The debug messenger of an instance with the layer; destroyed with the device.
pub(crate) struct Messenger {
    loader: ash::ext::debug_utils::Instance,
    handle: vk::DebugUtilsMessengerEXT,
}

impl Messenger {
    pub(crate) fn new(entry: &ash::Entry, instance: &ash::Instance) -> Result<Messenger> {
        let loader = ash::ext::debug_utils::Instance::new(entry, instance);
        // SAFETY: a valid instance created with VK_EXT_debug_utils; the callback is 'static.
        let handle = unsafe { loader.create_debug_utils_messenger(&messenger_info(), None) }
            .vk("vkCreateDebugUtilsMessengerEXT")?;
        Ok(Messenger { loader, handle })
    }

    /// # Safety
    /// Called once, before the instance is destroyed.
    pub(crate) unsafe fn destroy(&self) {
        self.loader.destroy_debug_utils_messenger(self.handle, None);
    }
}

/// The `VUID-...` (or `UNASSIGNED-...`) name of a message, or `"?"`.
fn message_id(data: &vk::DebugUtilsMessengerCallbackDataEXT<'_>) -> String {
    // SAFETY: the layer passes a NUL-terminated string or null.
    unsafe { data.message_id_name_as_c_str() }
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "?".into())
}

unsafe extern "system" fn callback(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _kind: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    _user: *mut c_void,
) -> vk::Bool32 {
    // Nothing here may unwind into the driver: every step is infallible or ignored.
    let Some(data) = data.as_ref() else { return vk::FALSE };
    let id = message_id(data);
    let text = data.message_as_c_str().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    if severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::ERROR) {
        let line = format!("{id}: {text}");
        eprintln!("velox: validation error {line}");
        if let Ok(mut first) = FIRST.lock() {
            if first.len() < KEPT {
                first.push(line.clone());
            }
        }
        // The recording of the command buffer the message names, else this thread's work. (A
        // thread being torn down no longer has its counts: the process's still counts.)
        // SAFETY: the layer passes `object_count` valid entries, or a null pointer with none.
        let objects = if data.object_count == 0 || data.p_objects.is_null() {
            &[][..]
        } else {
            std::slice::from_raw_parts(data.p_objects, data.object_count as usize)
        };
        match objects.iter().find(|o| o.object_type == vk::ObjectType::COMMAND_BUFFER) {
            Some(o) => {
                if let Ok(mut by) = BY_COMMAND_BUFFER.lock() {
                    match by.iter_mut().find(|(h, _)| *h == o.object_handle) {
                        Some((_, lines)) => lines.push(line),
                        None => by.push((o.object_handle, vec![line])),
                    }
                }
            }
            None => {
                let _ = THREAD.try_with(|t| {
                    if let Ok(mut t) = t.try_borrow_mut() {
                        if t.first.len() < KEPT {
                            t.first.push(line);
                        }
                        t.count += 1;
                    }
                });
            }
        }
        ERRORS.fetch_add(1, Ordering::AcqRel);
    } else {
        eprintln!("velox: validation warning {id}: {text}");
    }
    vk::FALSE
}
