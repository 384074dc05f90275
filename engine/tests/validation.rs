//! The validation checks can fail: a barrier left out on purpose is reported by the layer's
//! synchronization validation, and a kernel that reads past its binding by GPU-assisted
//! validation; either turns into [`Error::Validation`] at submit. Each case runs in a child
//! process of this binary (validation is chosen when a device is opened, and the other tests of
//! the binary share one device), with the engine's descriptor-set binding path, the one the layer
//! tracks (`engine/src/recorder.rs`).
//!
//! These tests need the Khronos validation layer (Debian: `vulkan-validationlayers`) and, for
//! GPU-assisted validation, the newer build of it in Debian's `chromium-common`; the README's
//! test command installs both, and each test fails with that instruction where one is missing.

mod common;
use common::*;

/// The library `tools/vvl/VkLayer_khronos_validation.json` loads.
const NEWER_LAYER: &str = "/usr/lib/chromium/libVkLayer_khronos_validation.so";

use std::process::Command;

use velox_engine::kernels::CAST_F32_TO_F16;
use velox_engine::ops::binary::{binary, Binary};
use velox_engine::ops::fill::fill;
use velox_engine::validation::{self, Mode};
use velox_engine::Error;

/// Runs `child` (an ignored test of this binary) in a process of its own with `VELOX_VALIDATE`
/// set to `mode` and descriptor sets forced; returns its stdout and stderr. GPU-assisted
/// validation takes the newer layer `tools/vvl/` names (Debian 12's 1.3.239 instruments
/// buffer accesses but reports none past a binding).
fn run_child(child: &str, mode: &str) -> String {
    let mut command = Command::new(std::env::current_exe().unwrap());
    command
        .args([child, "--exact", "--ignored", "--nocapture", "--test-threads", "1"])
        .env("VELOX_VALIDATE", mode)
        .env("VELOX_DISABLE", "push-descriptors")
        .env("VK_LAYER_SETTINGS_PATH", concat!(env!("CARGO_MANIFEST_DIR"), "/../vk_layer_settings.txt"));
    if mode == "gpu" {
        let layer = concat!(env!("CARGO_MANIFEST_DIR"), "/../tools/vvl");
        assert!(
            std::path::Path::new(NEWER_LAYER).exists(),
            "GPU-assisted validation needs the validation layer Debian's chromium-common ships \
             ({NEWER_LAYER}): apt-get install chromium-common"
        );
        command.env("VK_LAYER_PATH", layer);
    }
    let out = command.output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(
        !text.contains("does not find"),
        "these tests need the Khronos validation layer: apt-get install vulkan-validationlayers\n{text}"
    );
    assert!(out.status.success(), "{child} under VELOX_VALIDATE={mode} failed:\n{text}");
    assert!(text.contains("1 passed"), "{child} did not run:\n{text}");
    text
}

/// Would catch: a validation setup that cannot see this engine's accesses (the layer's
/// synchronization checks ignore buffers bound through push descriptors), a messenger that
/// does not count, or a submit that does not fail on a counted error.
#[test]
fn a_missing_barrier_is_reported() {
    let text = run_child("child_missing_barrier", "1");
    assert!(text.contains("SYNC-HAZARD-READ-AFTER-WRITE"), "{text}");
}

/// Would catch: a validation error blamed on whichever test submits next rather than on the one
/// whose work the layer reported: tests share one device on parallel threads.
#[test]
fn a_validation_error_fails_its_own_recording_not_another_threads() {
    let text = run_child("child_error_on_one_thread", "1");
    assert!(text.contains("the racing recording"), "{text}");
}

/// Would catch: GPU-assisted validation not enabled by `VELOX_VALIDATE=gpu`, or not able to see
/// a read past a binding of this engine's kernels.
#[test]
fn a_read_past_a_binding_is_reported() {
    let text = run_child("child_read_past_binding", "gpu");
    assert!(text.contains("VUID-vkCmdDispatch-storageBuffers-06936"), "{text}");
}

#[test]
#[ignore = "run by a_missing_barrier_is_reported in a process of its own"]
fn child_missing_barrier() {
    // A device of its own, dropped before the process ends (the layers tear down at exit).
    let gpu = Gpu::new().unwrap();
    assert_eq!(gpu.validation(), Mode::Sync);
    assert!(!gpu.caps().push_descriptors);
    let t = Tensor::empty(&gpu, &[4096], DType::F32).unwrap();
    // A write and a read of what it wrote: with its barrier, clean. (A write after a write of
    // one buffer would not do: the layer does not report those between dispatches.)
    let mut rec = gpu.recorder().unwrap();
    fill(&mut rec, &t, 1.0).unwrap();
    let sum = binary(&mut rec, &t, &t, Binary::Add).unwrap();
    rec.submit().unwrap();
    assert_eq!(sum.read::<f32>().unwrap()[4095], 2.0);
    assert_eq!(validation::error_count(), 0);
    // Without: the read races the write.
    let mut rec = gpu.recorder().unwrap();
    rec.set_hazard_tracking(false);
    fill(&mut rec, &t, 1.0).unwrap();
    binary(&mut rec, &t, &t, Binary::Add).unwrap();
    match rec.submit() {
        Err(Error::Validation(what)) => eprintln!("submit failed as it should: {what}"),
        other => panic!("a missing barrier went unreported: {:?}", other.map(|_| ())),
    }
    assert!(validation::error_count() > 0);
}

#[test]
#[ignore = "run by a_validation_error_fails_its_own_recording_not_another_threads in a process of its own"]
fn child_error_on_one_thread() {
    let gpu = Gpu::new().unwrap();
    assert_eq!(gpu.validation(), Mode::Sync);
    let t = Tensor::empty(&gpu, &[4096], DType::F32).unwrap();
    // One thread records a race (the layer reports it as the dispatch is recorded) and waits;
    // the other then submits clean work, and only after that does the first submit its race.
    let (raced, clean) = std::sync::mpsc::channel::<()>();
    let (go, wait) = std::sync::mpsc::channel::<()>();
    let racer = {
        let (gpu, t) = (gpu.clone(), t.clone());
        std::thread::spawn(move || {
            let mut rec = gpu.recorder().unwrap();
            rec.set_label("the racing recording");
            rec.set_hazard_tracking(false);
            fill(&mut rec, &t, 1.0).unwrap();
            binary(&mut rec, &t, &t, Binary::Add).unwrap();
            raced.send(()).unwrap();
            wait.recv().unwrap();
            rec.submit().map(|_| ())
        })
    };
    clean.recv().unwrap();
    let u = Tensor::empty(&gpu, &[4096], DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    fill(&mut rec, &u, 2.0).unwrap();
    let sum = binary(&mut rec, &u, &u, Binary::Add).unwrap();
    assert!(validation::error_count() > 0, "the race was not reported as it was recorded");
    rec.submit().expect("the clean thread's submit is not blamed for the other's race");
    assert_eq!(sum.read::<f32>().unwrap()[0], 4.0);
    go.send(()).unwrap();
    match racer.join().unwrap() {
        Err(Error::Validation(what)) => eprintln!("the race failed its own submit: {what}"),
        other => panic!("the race went unreported on its thread: {other:?}"),
    }
    assert_eq!(validation::unreported_count(), 0);
}

#[test]
#[ignore = "run by a_read_past_a_binding_is_reported in a process of its own"]
fn child_read_past_binding() {
    let gpu = Gpu::new().unwrap();
    assert_eq!(gpu.validation(), Mode::GpuAssisted);
    // A view of 64 elements inside a tensor of 1024, so that the stray reads stay in memory the
    // engine owns; the cast is told 256 elements, and its output holds them.
    let whole = Tensor::from_slice(&gpu, &[1024], &vec![1.0f32; 1024]).unwrap();
    let view = whole.view(0, &[64]).unwrap();
    let out = Tensor::empty(&gpu, &[256], DType::F16).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let told = velox_engine::kernels::params::CastParams { n: 256 };
    let args = velox_engine::kernels::args::CastF32ToF16Args { src_f32: &view, dst_f16: &out };
    rec.dispatch(CAST_F32_TO_F16, [1, 1, 1], args, &told).unwrap();
    match rec.submit() {
        Err(Error::Validation(what)) => eprintln!("submit failed as it should: {what}"),
        other => panic!("a read past the binding went unreported: {:?}", other.map(|_| ())),
    }
}
