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
//! the first few. [`Recorder::submit`](crate::Recorder::submit) fails with [`Error::Validation`]
//! when errors arrived since the last one it reported, so any test that submits work fails on
//! an error made by any earlier call; the `velox` command exits non-zero when the count is above
//! zero at its end ([`error_count`]). Asking for validation where the layer is not installed is
//! an error, not a silent run without it.

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

/// Messages of error severity since the process started.
static ERRORS: AtomicUsize = AtomicUsize::new(0);
/// The first [`KEPT`] of them, as printed.
static FIRST: Mutex<Vec<String>> = Mutex::new(Vec::new());
const KEPT: usize = 16;

/// Validation errors reported since the process started (0 when validation is off).
pub fn error_count() -> usize {
    ERRORS.load(Ordering::Acquire)
}

/// The first validation errors reported, each as `VUID: message`.
pub fn first_errors() -> Vec<String> {
    FIRST.lock().map(|v| v.clone()).unwrap_or_default()
}

/// The error [`Recorder::submit`](crate::Recorder::submit) returns when `count` errors are known,
/// `since` of them already reported.
pub(crate) fn failure(count: usize, since: usize) -> Error {
    let first = first_errors();
    let shown = first.get(since.min(first.len())).or(first.last()).cloned().unwrap_or_default();
    Error::Validation(format!(
        "{} new validation error(s), {count} in all; first new one: {shown}",
        count - since
    ))
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
                first.push(line);
            }
        }
        ERRORS.fetch_add(1, Ordering::AcqRel);
    } else {
        eprintln!("velox: validation warning {id}: {text}");
    }
    vk::FALSE
}
