//! What a GPU call brings back: `tools/device-results.sh` packs a device check's folder into the
//! few files the call returns, with `velox bench report`'s summary, and refuses, naming the file
//! and the limit, what would not come back. The limits are set low here (the call's are 8
//! files, 16 MiB each, 64 MiB in all, two folders deep).

use std::path::{Path, PathBuf};
use std::process::Command;

mod common;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("velox-device-check-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn write(path: &Path, text: &str) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, text).unwrap();
}

/// A device check's scratch folder: a device report, two test runs, a suite of records with
/// PyTorch's times for one, a training log, an evaluation, a weights file and logs nested
/// deeper than a call returns.
fn results(dir: &Path) {
    write(
        &dir.join("info.json"),
        r#"{"device": "Test GPU 9000", "kind": "discrete GPU", "driver": "test 1.0", "vulkan": "1.3.0",
            "subgroup_size": 32, "min_subgroup_size": 32, "max_subgroup_size": 32, "max_shared_memory": 49152,
            "device_memory_bytes": 1073741824, "f16_arithmetic": true, "float_atomic_add": true,
            "coop_matrix_shapes": ["16x16x16 f16*f16+f32->f32"], "variants": {"matmul f32": "tiled"}}"#,
    );
    write(&dir.join("phases.tsv"), "tests\tok\t12\tsee the Tests table\n");
    write(
        &dir.join("tests/ops.txt"),
        "running 3 tests\ntest a::one ... ok\ntest a::two ... FAILED\n\
         test result: FAILED. 2 passed; 1 failed; 0 ignored; 0 measured; 0 filtered out; finished in 1s\n",
    );
    write(&dir.join("tests/staging.txt"), "not run: no time left in its box\n");
    let record = |name: &str, ms: f64| {
        format!(
            r#"{{"name": "{name}", "shape": "64x64x64", "precision": "f32", "device": "Test GPU 9000",
                "median_ms": {ms}, "min_ms": {ms}, "repeats": 10, "throughput": 1.5, "throughput_unit": "TFLOP/s",
                "peak_fraction": 0.25, "nmse": 1e-14, "max_abs_err": 1e-6, "error_over": "all outputs", "gpu_timed": true}}"#
        )
    };
    write(
        &dir.join("bench/kernels.json"),
        &format!("[{}, {}]", record("matmul", 0.5), record("softmax", 0.2)),
    );
    write(
        &dir.join("bench/torch.json"),
        r#"{"peer": "torch", "torch_version": "2.11.0", "device": "Test GPU 9000", "policy": "the same",
            "records": [{"suite": "kernels", "name": "matmul", "shape": "64x64x64", "precision": "f32",
                         "torch_op": "torch.matmul", "median_ms": 0.25, "min_ms": 0.25, "repeats": 10, "note": ""}]}"#,
    );
    write(
        &dir.join("train/log.jsonl"),
        "{\"step\":1,\"seconds\":1.0,\"samples\":[\"a\"],\"loss\":{\"total\":2.0}}\n\
         {\"step\":2,\"seconds\":2.0,\"samples\":[\"b\"],\"loss\":{\"total\":1.5}}\n",
    );
    write(
        &dir.join("eval/eval.json"),
        r#"{"precision": "f16", "sampler": "heun", "steps": 20, "scenes": [{}, {}],
            "mean": {"psnr": 27.5, "ssim": 0.91, "chamfer": 0.001, "chamfer_gt_halves": 0.0005}}"#,
    );
    for i in 0..20 {
        write(&dir.join(format!("bench/deep/er/still/log{i}.txt")), &format!("line {i}\n"));
    }
    write(&dir.join("weights.safetensors"), &"w".repeat(3000));
    // The dataset and checkpoints stay behind.
    write(&dir.join("data/scene_00000/points.ply"), "ply");
    write(&dir.join("train/checkpoint.safetensors"), "checkpoint");
}

fn pack(work: &Path, out: &Path, limits: &[(&str, &str)]) -> std::process::Output {
    let mut cmd = Command::new(concat!(env!("CARGO_MANIFEST_DIR"), "/device-results.sh"));
    cmd.args([work, out]).env("VELOX_BIN", env!("CARGO_BIN_EXE_velox"));
    for (k, v) in limits {
        cmd.env(k, v);
    }
    cmd.output().unwrap()
}

/// Every file under `dir`, as paths relative to it, in name order.
fn files(dir: &Path) -> Vec<String> {
    common::files_under(dir).into_iter().map(|(name, _)| name).collect()
}

/// Would catch: a device check that returns more files than a call brings back, or deeper
/// ones, a summary missing a part of the results (the device, a failed test, a bench row and
/// its PyTorch ratio, training, evaluation), and logs or weights left out of what returns.
#[test]
fn results_pack_into_the_files_a_call_returns() {
    let dir = temp_dir("pack");
    let (work, out) = (dir.join("work"), dir.join("out"));
    results(&work);
    let done = pack(&work, &out, &[("RESULT_MAX_FILES", "8")]);
    assert!(done.status.success(), "{}", String::from_utf8_lossy(&done.stderr));
    assert_eq!(files(&out), ["logs.tar.gz", "summary.md", "weights.safetensors"]);
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    for needle in [
        "**Test GPU 9000**",
        "| ops | 2 | 1 | 0 | 0 | FAILED |",
        "- ops: a::two",
        "| staging | 0 | 0 | 0 | 0 | not run: no time left |",
        // 0.5 ms against PyTorch's 0.25: twice as slow.
        "| matmul | 64x64x64 | f32 | 0.5000 |",
        "| 0.2500 | 2.00 |",
        "PyTorch 2.11.0 on Test GPU 9000, 1 of our rows",
        "2 steps, loss 2.0000 at step 1 to 1.5000 at step 2",
        "2 held-out scenes (f16 precision, heun 20 steps): PSNR 27.50 dB",
        "- weights.safetensors (3000 bytes)",
    ] {
        assert!(summary.contains(needle), "the summary lacks {needle:?}:\n{summary}");
    }
    let listed = Command::new("tar").arg("tzf").arg(out.join("logs.tar.gz")).output().unwrap();
    let listed = String::from_utf8_lossy(&listed.stdout);
    assert!(
        listed.contains("./bench/deep/er/still/log19.txt") && listed.contains("./tests/ops.txt"),
        "{listed}"
    );
    assert!(!listed.contains("points.ply") && !listed.contains("checkpoint"), "{listed}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Would catch: results over a limit that the check lets through silently (the call would drop
/// them), or a refusal that does not name the file and the limit; and logs over the per-file
/// limit that are not split into parts that fit.
#[test]
fn results_over_a_limit_are_named_with_the_limit() {
    let dir = temp_dir("limits");
    let (work, out) = (dir.join("work"), dir.join("out"));
    results(&work);
    // Too many files: 3 made, 2 allowed.
    let refused = pack(&work, &out, &[("RESULT_MAX_FILES", "2")]);
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && err.contains("holds 3 files, over the limit of 2"), "{err}");
    // A file over the per-file limit: the logs are split into parts that fit, the weights
    // (which only `velox weights` may split) are named.
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let incompressible: String = (0..40_000)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            char::from(b'a' + (state >> 60) as u8)
        })
        .collect();
    write(&work.join("tests/big.txt"), &incompressible);
    let refused = pack(&work, &out, &[("RESULT_MAX_FILE_BYTES", "2500")]);
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success(), "{err}");
    assert!(err.contains("weights.safetensors: 3000 bytes, over the limit of 2500 bytes a file"), "{err}");
    let parts: Vec<String> = files(&out).into_iter().filter(|f| f.starts_with("logs.tar.gz.")).collect();
    assert!(parts.len() > 1, "{:?} {err}", files(&out));
    assert!(!err.contains("logs.tar.gz"), "a part of the logs is over the limit: {err}");
    let _ = std::fs::remove_dir_all(&dir);
}
