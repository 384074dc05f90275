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

/// Standard base64 with padding, for data: URIs.
pub fn base64(bytes: &[u8]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::new();
    for c in bytes.chunks(3) {
        let n = (c[0] as u32) << 16 | (*c.get(1).unwrap_or(&0) as u32) << 8 | *c.get(2).unwrap_or(&0) as u32;
        for k in 0..4 {
            if k <= c.len() {
                s.push(T[(n >> (18 - 6 * k)) as usize & 63] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

/// A GLB file of a JSON document and a binary chunk, each padded to 4 bytes.
pub fn glb(json: &str, bin: &[u8]) -> Vec<u8> {
    let mut j = json.as_bytes().to_vec();
    while !j.len().is_multiple_of(4) {
        j.push(b' ');
    }
    let mut b = bin.to_vec();
    while !b.len().is_multiple_of(4) {
        b.push(0);
    }
    let total = 12 + 8 + j.len() + 8 + b.len();
    let mut out = Vec::new();
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((j.len() as u32).to_le_bytes());
    out.extend(0x4E4F_534Au32.to_le_bytes());
    out.extend(j);
    out.extend((b.len() as u32).to_le_bytes());
    out.extend(0x004E_4942u32.to_le_bytes());
    out.extend(b);
    out
}
