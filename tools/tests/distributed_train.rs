//! `velox train` as two MPI processes against one process accumulating two micro-batches: the
//! same samples, the same draws, the gradients summed across the processes instead of into one
//! buffer, so the runs end with the same parameters. `cargo test --release --test
//! distributed_train` (Open MPI's `openmpi-bin` installed).

use std::path::Path;
use std::process::{Command, Output};

fn velox() -> Command {
    Command::new(env!("CARGO_BIN_EXE_velox"))
}

fn arg(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `mpirun` for two processes, each free to run on any core as the single-process run is:
/// Open MPI binds each process to a core by default, and lavapipe's results depend on the cores
/// a process may use (the Gaussian decoder's outputs move by an ulp when a process is bound to
/// one core, measured on an AMD EPYC machine; same binding, same bits), which would make the
/// two runs differ for a reason that is not the all-reduce.
fn mpirun() -> Command {
    let mut c = Command::new("mpirun");
    c.args(["--allow-run-as-root", "--oversubscribe", "--bind-to", "none", "--timeout", "300", "-np", "2"]);
    c
}

#[path = "../../tests/support/mpi.rs"]
mod mpi;
use mpi::mpirun_present;

fn ok(out: Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{:?}\n{err}", out.status);
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn two_processes_train_as_one_accumulating_two_micro_batches() {
    use velox_models::checkpoint::read_tensors;
    if !mpirun_present() {
        return;
    }

    let dir = std::env::temp_dir().join(format!("velox-distributed-train-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let data = dir.join("data");
    ok(velox()
        .args(["data", "synth", "--out", arg(&data), "--scenes", "2", "--res", "24", "--points", "1500"])
        .output()
        .unwrap());
    let train = ["train", "autoencoder", "--data", arg(&data), "--config", "tiny", "--steps", "4"];
    let (two, one) = (dir.join("two"), dir.join("one"));
    let said = ok(mpirun()
        .arg(env!("CARGO_BIN_EXE_velox"))
        .args(train)
        .args(["--steps-per-scene", "2", "--out", arg(&two)])
        .output()
        .unwrap());
    // Process 0 alone reports (and writes the files).
    assert_eq!(said.matches("trained 4 steps").count(), 1, "{said}");
    ok(velox()
        .args(train)
        .args(["--steps-per-scene", "2", "--accumulate", "2", "--out", arg(&one)])
        .output()
        .unwrap());

    let ((info_two, a), (info_one, b)) = (
        read_tensors(&two.join("checkpoint.safetensors")).unwrap(),
        read_tensors(&one.join("checkpoint.safetensors")).unwrap(),
    );
    assert_eq!((info_two.step, info_one.step), (4, 4));
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    let (mut diff, mut norm) = (0f64, 0f64);
    for (name, x) in &a {
        for (p, q) in x.iter().zip(&b[name]) {
            diff += (*p as f64 - *q as f64).powi(2);
            norm += (*q as f64).powi(2);
        }
    }
    let nmse = diff / norm;
    eprintln!("two processes against one accumulating two: NMSE {nmse:.2e} over every tensor");
    assert!(nmse < 1e-12, "NMSE {nmse:e}");
    // The logs agree too: the same samples and losses at every step.
    let log = |run: &Path| -> Vec<serde_json::Value> {
        std::fs::read_to_string(run.join("log.jsonl"))
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .collect()
    };
    let (la, lb) = (log(&two), log(&one));
    assert_eq!(la.len(), 4);
    for (x, y) in la.iter().zip(&lb) {
        assert_eq!(x["samples"], y["samples"]);
        let (p, q) = (x["loss"]["total"].as_f64().unwrap(), y["loss"]["total"].as_f64().unwrap());
        assert!((p - q).abs() <= 1e-9 * q.abs(), "step {}: loss {p} against {q}", x["step"]);
    }

    // A run of two processes stopped at step 2 resumes as one process (accumulating two
    // micro-batches to keep the batch) and ends where the uninterrupted run did.
    let resumed = dir.join("resumed");
    ok(mpirun()
        .arg(env!("CARGO_BIN_EXE_velox"))
        .args(train)
        .args(["--steps-per-scene", "2", "--stop-at", "2", "--out", arg(&resumed)])
        .output()
        .unwrap());
    let out = velox().args(train).args(["--resume", "--out", arg(&resumed)]).output().unwrap();
    let note = String::from_utf8_lossy(&out.stderr).into_owned();
    ok(out);
    assert!(note.contains("accumulat"), "the resumption says how it keeps the batch: {note}");
    let (_, c) = read_tensors(&resumed.join("checkpoint.safetensors")).unwrap();
    assert!(c == a, "the resumed run's parameters differ from the uninterrupted run's");
    let _ = std::fs::remove_dir_all(&dir);
}
