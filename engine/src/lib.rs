//! velox-engine: a small tensor runtime written directly on Vulkan compute.
//!
//! - [`Gpu`] opens a device ([`device`]) and reads its features ([`caps`]);
//! - [`Tensor`] holds device memory ([`tensor`]);
//! - kernels are WGSL files in `shaders/`, compiled to SPIR-V by naga at build time
//!   ([`kernels`]);
//! - a [`Recorder`] batches dispatches into one command buffer with the barriers they need
//!   ([`recorder`]);
//! - [`validation`] counts the Khronos validation layer's errors under `VELOX_VALIDATE`;
//! - [`ops`] holds each op's host side next to its f64 CPU reference.

pub mod caps;
pub mod device;
pub mod error;
pub mod kernels;
pub mod ops;
pub mod profile;
pub mod recorder;
pub mod rng;
pub mod stats;
pub mod tensor;
pub mod validation;

pub use caps::{Caps, Switches};
pub use device::{list_devices, DeviceSummary, Gpu};
pub use error::{fit_u32, Error, Feature, FileOp, Limit, Result};
pub use recorder::{Completion, Finished, Launched, NarrowMatmul, Precision, Recorder};
pub use tensor::{DType, Element, Readback, Tensor};
