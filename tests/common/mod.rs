//! Shared by the test binaries: one device for all tests of a binary.
#![allow(dead_code, unused_imports)]

use std::sync::OnceLock;

pub use velox::engine::rng::Rng;
pub use velox::engine::stats::{max_abs_err, nmse};
pub use velox::engine::{DType, Gpu, Tensor};

/// The device every test of this binary shares (lavapipe in CI).
pub fn gpu() -> Gpu {
    static GPU: OnceLock<Gpu> = OnceLock::new();
    GPU.get_or_init(|| Gpu::new().unwrap_or_else(|e| panic!("tests need a Vulkan device: {e}"))).clone()
}

/// f32 data to f64 for the references.
pub fn f64s(x: &[f32]) -> Vec<f64> {
    x.iter().map(|&v| v as f64).collect()
}

/// Asserts an NMSE bound with a message that shows the figures.
#[track_caller]
pub fn assert_nmse(what: &str, got: &[f32], reference: &[f64], bound: f64) {
    let e = nmse(got, reference);
    let m = max_abs_err(got, reference);
    if std::env::var_os("VELOX_TEST_VERBOSE").is_some() {
        eprintln!("{what}: nmse {e:.2e} max abs {m:.2e} (bound {bound:.0e})");
    }
    assert!(e <= bound, "{what}: nmse {e:.3e} > bound {bound:.1e} (max abs err {m:.3e})");
}
