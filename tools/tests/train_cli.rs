//! `velox train autoencoder` as a user meets it when things go wrong: a loss that becomes NaN,
//! a run interrupted by SIGINT or SIGTERM, and a run stopped and resumed, which must repeat
//! the uninterrupted run.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn velox() -> Command {
    Command::new(env!("CARGO_BIN_EXE_velox"))
}

fn arg(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A folder of this test process for `name`, empty.
fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("velox-train-cli-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Two small scenes (24 px, 1500 points), made once for every test of this file.
fn dataset() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = temp_dir("data").join("data");
        let out = velox()
            .args(["data", "synth", "--out", arg(&dir), "--scenes", "2", "--res", "24", "--points", "1500"])
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", stderr(&out));
        dir
    })
}

/// The tiny config with another peak learning rate and no warm-up, as a config file.
fn tiny_config_with_lr(dir: &Path, lr: f64) -> PathBuf {
    let out = velox().args(["config", "tiny"]).output().unwrap();
    let mut cfg: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    cfg["peak_lr"] = lr.into();
    cfg["warmup"] = 1.into();
    let path = dir.join(format!("lr{lr:e}.json"));
    std::fs::write(&path, cfg.to_string()).unwrap();
    path
}

#[test]
fn a_nan_stop_calls_the_checkpoint_good_only_when_its_values_are_finite() {
    let dir = temp_dir("nan");
    // A learning rate of 1e30 makes step 1's parameters huge but finite, and step 2's
    // gradients overflow; one of 1e39 (Inf in f32) already writes Inf and NaN into the
    // parameters at step 1, so the checkpoint written then is no good.
    for (lr, good) in [(1e30, true), (1e39, false)] {
        let config = tiny_config_with_lr(&dir, lr);
        let out_dir = dir.join(format!("run{lr:e}"));
        let out = velox()
            .args(["train", "autoencoder", "--data", arg(dataset()), "--config", arg(&config)])
            .args(["--out", arg(&out_dir), "--steps", "6", "--checkpoint-every", "1"])
            .output()
            .unwrap();
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(err.contains("training stopped at step 2"), "{err}");
        let ckpt = out_dir.join("checkpoint.safetensors");
        if good {
            let said = format!(
                "the last good checkpoint is {} (step 1, every value checked finite)",
                ckpt.display()
            );
            assert!(err.contains(&said), "{err}");
        } else {
            assert!(!err.contains("last good"), "{err}");
            assert!(err.contains("the checkpoint is no good either") && err.contains("NaN or Inf"), "{err}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
