//! Shared by the test binaries of the engine (and, through the root tests' `common`, by every
//! other): a device for each test running at once, and the checks of a result against its f64
//! reference.
#![allow(dead_code, unused_imports)]

pub use velox_engine::rng::Rng;
pub use velox_engine::stats::{max_abs_err, nmse};
pub use velox_engine::{DType, Gpu, Precision, Tensor};

/// The device of this test's thread (lavapipe in CI). The binary keeps a pool of devices and
/// lends each test thread one that no other running test holds, for as long as the thread
/// lives (libtest runs each test on a thread of its own): tests running at once then submit to
/// queues of their own, which lavapipe runs side by side, where one shared queue would run
/// their work one submission at a time (the models binary: 206 -> 136 s on 2 cores). A device
/// returns to the pool when its thread ends: the first stays open for the next test, the
/// others are closed (see [`Lease`]), so a binary has at most as many open as tests run at
/// once (`--test-threads`). Under GPU-assisted validation and on SwiftShader the binary has one
/// device, which every test shares: both crash at exit once a second one has been open.
pub fn gpu() -> Gpu {
    LEASE.with(|lease| {
        let mut lease = lease.borrow_mut();
        if lease.is_none() {
            let mut pool = POOL.lock().unwrap_or_else(|e| e.into_inner());
            if pool.is_empty() {
                // SAFETY: `close_shared` is a plain function that neither unwinds nor returns a value.
                unsafe { atexit(close_shared) };
            }
            // GPU-assisted validation and SwiftShader crash at exit once a second device has
            // been open: there every test shares the first.
            let shared = pool.first().and_then(|(g, _)| g.as_ref()).is_some_and(devices_shared);
            let slot = match pool.iter().position(|(_, holders)| *holders == 0) {
                Some(i) => i,
                None if shared => 0,
                None => {
                    pool.push((None, 0));
                    pool.len() - 1
                }
            };
            if pool[slot].0.is_none() {
                let gpu = Gpu::new().unwrap_or_else(|e| panic!("tests need a Vulkan device: {e}"));
                pool[slot].0 = Some(gpu);
            }
            pool[slot].1 += 1;
            *lease = Some(Lease { slot, gpu: pool[slot].0.clone().expect("closed only at exit") });
        }
        lease.as_ref().expect("leased above").gpu.clone()
    })
}

/// Whether the tests share `gpu`, the binary's one device (GPU-assisted validation and
/// SwiftShader, see [`gpu`]); elsewhere a test's device is its own while it runs, so that a
/// count of the device's submissions (`Gpu::submits`) is the test's alone. A test never opens
/// a device of its own for that: one more device crashes those two at exit, and Debian 12's
/// validation layer too when it is the process's first.
pub fn devices_shared(gpu: &Gpu) -> bool {
    velox_engine::validation::Mode::from_env().is_ok_and(|m| m == velox_engine::validation::Mode::GpuAssisted)
        || gpu.caps().name.contains("SwiftShader")
}

/// This test's device while it runs, for a test that counts its submissions; `None`, saying
/// so, where the tests share one device ([`devices_shared`]).
pub fn counting_gpu() -> Option<Gpu> {
    let gpu = gpu();
    if devices_shared(&gpu) {
        eprintln!("the tests share one device here: its submissions are not this test's alone, not counted");
        return None;
    }
    Some(gpu)
}

/// The binary's devices, each with the number of running tests' threads that hold it.
static POOL: std::sync::Mutex<Vec<(Option<Gpu>, usize)>> = std::sync::Mutex::new(Vec::new());

/// A thread's hold on a device of the pool, given back when the thread ends.
struct Lease {
    slot: usize,
    gpu: Gpu,
}

impl Drop for Lease {
    /// Gives the device back; a device other than the first is closed once no thread holds it
    /// (the next test to need a second one opens it again), so that only the first is open
    /// when the process exits: validation layers crash (Debian 12's, destroying a second
    /// instance at exit) or abort (sid's, finding one still open) otherwise.
    fn drop(&mut self) {
        let closing = POOL.lock().ok().and_then(|mut pool| {
            let entry = pool.get_mut(self.slot)?;
            entry.1 = entry.1.saturating_sub(1);
            if self.slot > 0 && entry.1 == 0 {
                entry.0.take()
            } else {
                None
            }
        });
        // Closed outside the pool's lock (the last handle is this lease's own, dropped after).
        drop(closing);
    }
}

thread_local! {
    static LEASE: std::cell::RefCell<Option<Lease>> = const { std::cell::RefCell::new(None) };
}

extern "C" {
    fn atexit(f: extern "C" fn()) -> std::ffi::c_int;
    fn _exit(status: std::ffi::c_int) -> !;
}

/// Closes the pool's devices (the last handles, once every test is done with them: by then
/// only the first is open), and fails the process when the validation layer reported errors
/// that no test's submit reported (work that never submitted after its error): every error
/// fails the run, and each submitted one fails the test whose thread made it.
extern "C" fn close_shared() {
    let devices: Vec<Gpu> =
        POOL.lock().map(|mut p| p.iter_mut().filter_map(|(g, _)| g.take()).collect()).unwrap_or_default();
    drop(devices);
    let unreported = velox_engine::validation::unreported_count();
    if unreported > 0 {
        eprintln!(
            "{unreported} validation error(s) arrived after the last submit of the work that made them:"
        );
        for line in velox_engine::validation::first_errors() {
            eprintln!("  {line}");
        }
        // SAFETY: ends the process at once, as exit() may not be called again from an atexit handler.
        unsafe { _exit(1) };
    }
}

/// Whether `bytes` bind as one storage buffer on this device. Where they do not (a binding
/// limit forced below them with `VELOX_MAX_BINDING`: real devices bind at least 128 MiB),
/// `attempt`, the op on such a tensor, must be refused with the engine's error that names the
/// limit; the caller then skips the case.
pub fn binds_or_refused<T>(
    gpu: &Gpu,
    bytes: usize,
    attempt: impl FnOnce() -> velox_engine::Result<T>,
) -> bool {
    if bytes as u64 <= gpu.caps().max_storage_buffer_range {
        return true;
    }
    match attempt() {
        Err(velox_engine::Error::TooLarge { limit: velox_engine::Limit::Binding, .. }) => {}
        Err(e) => panic!("a tensor of {bytes} bytes past the binding limit: {e}"),
        Ok(_) => panic!("a tensor of {bytes} bytes past the binding limit was not refused"),
    }
    false
}

/// f32 data to f64 for the references.
pub fn f64s(x: &[f32]) -> Vec<f64> {
    x.iter().map(|&v| v as f64).collect()
}

/// Whether the tests were asked to print their measurements (`VELOX_TEST_VERBOSE=1`).
pub fn verbose() -> bool {
    std::env::var_os("VELOX_TEST_VERBOSE").is_some()
}

/// Asserts an NMSE bound with a message that shows the figures.
#[track_caller]
pub fn assert_nmse(what: &str, got: &[f32], reference: &[f64], bound: f64) {
    let e = nmse(got, reference);
    let m = max_abs_err(got, reference);
    if verbose() {
        eprintln!("{what}: nmse {e:.2e} max abs {m:.2e} (bound {bound:.0e})");
    }
    assert!(e <= bound, "{what}: nmse {e:.3e} > bound {bound:.1e} (max abs err {m:.3e})");
}

/// `n` random Gaussians in front of the identity camera, spread over its view (log-scales and
/// opacity logits drawn from the ranges given).
pub fn random_gaussians(
    n: usize,
    seed: u64,
    log_scale: (f64, f64),
    logit: (f64, f64),
) -> velox_engine::ops::raster::GaussianData {
    let mut rng = Rng::new(seed);
    let mut g = velox_engine::ops::raster::GaussianData::default();
    for _ in 0..n {
        let z = rng.range(2.0, 5.0);
        let mean = [rng.range(-0.6, 0.6) * z, rng.range(-0.45, 0.45) * z, z].map(|v| v as f32);
        let ls = [0; 3].map(|_| rng.range(log_scale.0, log_scale.1) as f32);
        let q = [0; 4].map(|_| rng.normal() as f32);
        let o = rng.range(logit.0, logit.1) as f32;
        let c = [0; 3].map(|_| rng.uniform() as f32);
        g.push(mean, ls, q, o, c);
    }
    g
}
