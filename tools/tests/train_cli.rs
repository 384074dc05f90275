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

/// Steps in a run's log.jsonl.
fn logged_steps(log: &Path) -> Vec<u64> {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .map(|l| l["step"].as_u64().unwrap())
        .collect()
}

#[cfg(unix)]
/// Starts `velox train autoencoder` into `out` (1000 steps, no periodic checkpoint, `extra`
/// arguments) and returns once its log shows `steps` steps.
fn start_training(out: &Path, extra: &[&str], steps: usize) -> std::process::Child {
    use std::process::Stdio;
    let mut child = velox()
        .args(["train", "autoencoder", "--data", arg(dataset()), "--config", "tiny", "--out", arg(out)])
        .args(["--steps", "1000", "--checkpoint-every", "1000"])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let log = out.join("log.jsonl");
    while logged_steps(&log).len() < steps {
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut err).unwrap();
            panic!("the run ended ({status}) before step {steps}: {err}");
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child
}

#[cfg(unix)]
fn send(child: &std::process::Child, signal: i32) {
    // SAFETY: kill(2) on the id of a child this test started and has not yet waited for.
    assert_eq!(unsafe { libc::kill(child.id() as i32, signal) }, 0);
}

#[cfg(unix)]
#[test]
fn sigint_and_sigterm_finish_the_step_and_write_the_checkpoint() {
    use std::os::unix::process::ExitStatusExt;
    use velox_models::checkpoint;

    let dir = temp_dir("signals");
    for (signal, name, code) in [(libc::SIGINT, "SIGINT", 130), (libc::SIGTERM, "SIGTERM", 143)] {
        let out = dir.join(name);
        let child = start_training(&out, &[], 3);
        send(&child, signal);
        let done = child.wait_with_output().unwrap();
        let err = stderr(&done);
        assert_eq!(done.status.code(), Some(code), "{name}: {:?}\n{err}", done.status);
        let ckpt = out.join("checkpoint.safetensors");
        let step = *logged_steps(&out.join("log.jsonl")).last().unwrap();
        assert!(step >= 3);
        let said = format!(
            "{name}: stopped after step {step} of 1000; checkpoint {} holds step {step}",
            ckpt.display()
        );
        assert!(err.contains(&said), "{err}");
        assert!(!err.contains("error"), "{err}");
        assert_eq!(
            checkpoint::verify_finite(&ckpt).unwrap().step,
            step,
            "the checkpoint is at the last logged step"
        );
    }

    // Two signals in a row: the run stops as above, or the second ends it at once (depending on
    // when they land). Either way the checkpoint on disk is whole: the one just written or the
    // one the run resumed from.
    let out = dir.join("SIGINT");
    let before = checkpoint::peek(&out.join("checkpoint.safetensors")).unwrap().step;
    let child = start_training(&out, &["--resume"], before as usize + 3);
    send(&child, libc::SIGINT);
    send(&child, libc::SIGINT);
    let done = child.wait_with_output().unwrap();
    let err = stderr(&done);
    let stopped = done.status.code() == Some(130) && err.contains("stopped after step");
    assert!(stopped || done.status.signal() == Some(libc::SIGINT), "{:?}\n{err}", done.status);
    let after = checkpoint::verify_finite(&out.join("checkpoint.safetensors")).unwrap().step;
    let last = *logged_steps(&out.join("log.jsonl")).last().unwrap();
    assert!(
        after == before || (stopped && after == last),
        "checkpoint at {after}: resumed at {before}, logged {last}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
