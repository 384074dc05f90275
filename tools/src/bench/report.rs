//! `velox bench report DIR`: one Markdown page from a folder of results, as
//! `tools/device-check.sh` and `tools/bench-all.sh` leave them: the device, the phases and
//! their times, every test run (passed, failed, validation errors, the failing tests' names),
//! every benchmark row beside PyTorch's time at the same shape and the ratio, the training run
//! and the evaluation. Each part is read where it is found and said missing where it is not, so
//! a run cut short still reports what it finished.
//!
//! Layout read (each part optional): `info.json` (`velox info --json`), `phases.tsv` (name,
//! status, seconds, note: a line a phase), `tests/*.txt` (test binaries' output), `bench/*.json`
//! (`velox bench --json` record lists; `bench/torch.json` from `tools/peers/torch_bench.py`),
//! `train/` (`config.json`, `log.jsonl`, `train.txt`) and `eval/eval.json`. Without a `bench/`
//! folder, record lists at the top of DIR are read instead (a `bench-all.sh` folder). The parsing
//! is tested in `tools/tests/device_check.rs`.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::CliResult;

#[derive(clap::Args)]
pub struct ReportArgs {
    /// The folder of results.
    dir: PathBuf,
    /// Write the page here (default: print it).
    #[arg(long)]
    out: Option<PathBuf>,
}

pub fn run(a: &ReportArgs) -> CliResult<()> {
    if !a.dir.is_dir() {
        return Err(format!("{}: not a folder of results", a.dir.display()).into());
    }
    let page = report(&a.dir);
    match &a.out {
        Some(path) => {
            velox_io::write_bytes(path, page.as_bytes())?;
            println!("wrote {}", path.display());
        }
        None => print!("{page}"),
    }
    Ok(())
}

fn read_json(path: &Path) -> Option<Value> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// The page for the results in `dir`.
pub fn report(dir: &Path) -> String {
    let mut page = String::from("# Velox on this device\n\n");
    let info = read_json(&dir.join("info.json"));
    let cpu = info.as_ref().is_some_and(|i| i["kind"] == "CPU");
    device_section(&mut page, info.as_ref());
    phases_section(&mut page, dir);
    tests_section(&mut page, dir);
    bench_section(&mut page, dir, cpu);
    training_section(&mut page, dir);
    eval_section(&mut page, dir);
    page
}

fn device_section(page: &mut String, info: Option<&Value>) {
    page.push_str("## Device\n\n");
    let Some(i) = info else {
        page.push_str("No device report (info.json is missing: `velox info` did not run or failed).\n\n");
        return;
    };
    let text = |k: &str| i[k].as_str().map(str::to_string).unwrap_or_else(|| i[k].to_string());
    let _ = writeln!(
        page,
        "- **{}** ({}), driver {}, Vulkan {}",
        text("device"),
        text("kind"),
        text("driver"),
        text("vulkan")
    );
    let _ = writeln!(
        page,
        "- subgroups {} ({}..{}), {} KiB shared memory, {:.0} MiB device memory",
        i["subgroup_size"],
        i["min_subgroup_size"],
        i["max_subgroup_size"],
        i["max_shared_memory"].as_u64().unwrap_or(0) / 1024,
        i["device_memory_bytes"].as_f64().unwrap_or(0.0) / (1u64 << 20) as f64
    );
    let coop = i["coop_matrix_shapes"].as_array().map(|a| a.len()).unwrap_or(0);
    let _ = writeln!(
        page,
        "- f16 {}, f32 atomics {}, cooperative matrices: {}",
        yes(&i["f16_arithmetic"]),
        yes(&i["float_atomic_add"]),
        if coop == 0 {
            "none".to_string()
        } else {
            i["coop_matrix_shapes"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(Value::as_str)
                .collect::<Vec<_>>()
                .join(", ")
        }
    );
    if let Some(probe) = i.get("subgroup_probe") {
        let _ = writeln!(
            page,
            "- subgroup probe: builtin {}, lanes counted {}",
            probe["builtin"], probe["lanes"]
        );
    }
    if let Some(v) = i["variants"].as_object() {
        page.push_str("- kernel variants:\n");
        for (k, v) in v {
            let _ = writeln!(page, "  - {k}: {}", v.as_str().unwrap_or(""));
        }
    }
    if i["kind"] == "CPU" {
        page.push_str(
            "\nA CPU device (lavapipe or SwiftShader): every figure below is a CPU figure, not a GPU's.\n",
        );
    }
    page.push('\n');
}

fn yes(v: &Value) -> &'static str {
    if v.as_bool() == Some(true) {
        "yes"
    } else {
        "no"
    }
}

fn phases_section(page: &mut String, dir: &Path) {
    let Ok(text) = std::fs::read_to_string(dir.join("phases.tsv")) else { return };
    page.push_str("## Phases\n\n| phase | status | seconds | note |\n|---|---|---|---|\n");
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        let f: Vec<&str> = line.splitn(4, '\t').collect();
        let at = |i: usize| f.get(i).copied().unwrap_or("");
        let _ = writeln!(page, "| {} | {} | {} | {} |", at(0), at(1), at(2), at(3));
    }
    page.push('\n');
}

/// What one test binary's output says.
#[derive(Debug, Default, PartialEq)]
pub struct TestRun {
    pub passed: u64,
    pub failed: u64,
    pub ignored: u64,
    /// Names of the tests reported FAILED.
    pub failures: Vec<String>,
    /// Lines the engine printed for validation errors.
    pub validation_errors: u64,
    /// Whether a `test result` line was seen (else the binary was cut or crashed early).
    pub finished: bool,
}

/// Parses libtest's output (every `test result:` line is summed: a binary may run several).
pub fn parse_tests(text: &str) -> TestRun {
    let mut run = TestRun::default();
    for line in text.lines() {
        if let Some(rest) = line.strip_prefix("test result: ") {
            run.finished = true;
            for part in rest.split(';') {
                let words: Vec<&str> = part.split_whitespace().collect();
                let n = |i: usize| words.get(i).and_then(|w| w.parse::<u64>().ok());
                // "ok. 97 passed" or "FAILED. 2 passed", then "1 failed", "0 ignored".
                let (count, what) = match words.as_slice() {
                    [_, _, w, ..] if w.ends_with("passed") => (n(1), "passed"),
                    [_, w, ..] => (n(0), *w),
                    _ => (None, ""),
                };
                match (count, what) {
                    (Some(c), "passed") => run.passed += c,
                    (Some(c), "failed") => run.failed += c,
                    (Some(c), "ignored") => run.ignored += c,
                    _ => {}
                }
            }
        } else if let Some(name) = line.strip_prefix("test ").and_then(|l| l.strip_suffix(" ... FAILED")) {
            run.failures.push(name.to_string());
        } else if line.contains("velox: validation error") {
            run.validation_errors += 1;
        }
    }
    run
}

fn tests_section(page: &mut String, dir: &Path) {
    let Some(files) = sorted_files(&dir.join("tests"), "txt") else { return };
    page.push_str("## Tests\n\n| run | passed | failed | ignored | validation errors | result |\n|---|---|---|---|---|---|\n");
    let mut failures = Vec::new();
    for f in files {
        let text = std::fs::read_to_string(&f).unwrap_or_default();
        let run = parse_tests(&text);
        let name = f.file_stem().and_then(|s| s.to_str()).unwrap_or("?").to_string();
        let result = if text.starts_with("not run") {
            "not run: no time left"
        } else if !run.finished {
            "cut or crashed before its summary"
        } else if run.failed > 0 || run.validation_errors > 0 {
            "FAILED"
        } else {
            "ok"
        };
        let _ = writeln!(
            page,
            "| {name} | {} | {} | {} | {} | {result} |",
            run.passed, run.failed, run.ignored, run.validation_errors
        );
        failures.extend(run.failures.iter().map(|t| format!("{name}: {t}")));
    }
    if !failures.is_empty() {
        page.push_str("\nFailed:\n");
        for f in failures {
            let _ = writeln!(page, "- {f}");
        }
    }
    page.push('\n');
}

fn sorted_files(dir: &Path, ext: &str) -> Option<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .collect();
    files.sort();
    Some(files)
}

/// PyTorch's times by (name, shape, precision), with what it ran.
type PeerTimes = BTreeMap<(String, String, String), (f64, String)>;

fn key(r: &Value) -> (String, String, String) {
    let s = |k: &str| r[k].as_str().unwrap_or("").to_string();
    (s("name"), s("shape"), s("precision"))
}

fn bench_section(page: &mut String, dir: &Path, cpu: bool) {
    let bench = dir.join("bench");
    let folder = if bench.is_dir() { bench } else { dir.to_path_buf() };
    let Some(files) = sorted_files(&folder, "json") else { return };
    let torch = read_json(&folder.join("torch.json"));
    let mut peer = PeerTimes::new();
    if let Some(t) = &torch {
        for r in t["records"].as_array().into_iter().flatten() {
            if let Some(ms) = r["median_ms"].as_f64() {
                peer.insert(key(r), (ms, r["torch_op"].as_str().unwrap_or("").to_string()));
            }
        }
    }
    let mut any = false;
    let mut matched = 0usize;
    let mut body = String::new();
    for f in &files {
        let Some(Value::Array(records)) = read_json(f) else { continue };
        if records.first().is_none_or(|r| r.get("median_ms").is_none()) {
            continue;
        }
        any = true;
        let suite = f.file_stem().and_then(|s| s.to_str()).unwrap_or("?");
        let _ = writeln!(
            body,
            "### {suite}\n\n| kernel | shape | precision | median ms | throughput | % peak | nmse | max abs | PyTorch ms | ours / PyTorch |\n|---|---|---|---|---|---|---|---|---|---|"
        );
        for r in &records {
            let ms = r["median_ms"].as_f64().unwrap_or(f64::NAN);
            let (torch_ms, ratio) = match peer.get(&key(r)) {
                Some(&(t, _)) => {
                    matched += 1;
                    (format!("{t:.4}"), format!("{:.2}", ms / t))
                }
                None => ("-".into(), "-".into()),
            };
            let peak = r["peak_fraction"].as_f64().map(|p| format!("{:.1}", 100.0 * p)).unwrap_or("-".into());
            let _ = writeln!(
                body,
                "| {} | {} | {} | {ms:.4} | {:.4} {} | {peak} | {:.2e} | {:.2e} | {torch_ms} | {ratio} |",
                r["name"].as_str().unwrap_or(""),
                r["shape"].as_str().unwrap_or(""),
                r["precision"].as_str().unwrap_or(""),
                r["throughput"].as_f64().unwrap_or(0.0),
                r["throughput_unit"].as_str().unwrap_or(""),
                r["nmse"].as_f64().unwrap_or(0.0),
                r["max_abs_err"].as_f64().unwrap_or(0.0),
            );
        }
        body.push('\n');
    }
    if !any {
        return;
    }
    page.push_str("## Benchmarks\n\n");
    if cpu {
        page.push_str("CPU figures (a software Vulkan device).\n\n");
    }
    match &torch {
        Some(t) => {
            let _ = writeln!(
                page,
                "PyTorch {} on {}, {} of our rows timed beside ours at the same shapes and precisions ({}).\n",
                t["torch_version"].as_str().unwrap_or("?"),
                t["device"].as_str().unwrap_or("?"),
                matched,
                t["policy"].as_str().unwrap_or("policy not stated")
            );
        }
        None => page.push_str(
            "PyTorch: not measured (no bench/torch.json: `import torch` failed or the peer did not run).\n\n",
        ),
    }
    page.push_str(
        "Ours: one warm-up, then the repeats, each in its own submission timed by GPU timestamps, median; no L2 flush.\n\n",
    );
    page.push_str(&body);
}

fn training_section(page: &mut String, dir: &Path) {
    let train = dir.join("train");
    let Ok(log) = std::fs::read_to_string(train.join("log.jsonl")) else { return };
    let steps: Vec<Value> = log.lines().filter_map(|l| serde_json::from_str(l).ok()).collect();
    page.push_str("## Training\n\n");
    if let Some(cfg) = read_json(&train.join("config.json")) {
        let _ = writeln!(
            page,
            "- config {} (micro-batch {})",
            cfg["name"].as_str().unwrap_or("?"),
            cfg["batch"].as_u64().map(|b| b.to_string()).unwrap_or("?".into())
        );
    }
    if let (Some(first), Some(last)) = (steps.first(), steps.last()) {
        let loss = |s: &Value| s["loss"]["total"].as_f64().unwrap_or(f64::NAN);
        let samples: usize = steps.iter().map(|s| s["samples"].as_array().map_or(0, Vec::len)).sum();
        let seconds = last["seconds"].as_f64().unwrap_or(0.0);
        let _ = writeln!(
            page,
            "- {} steps, loss {:.4} at step {} to {:.4} at step {}; {samples} samples in {seconds:.0} s ({:.2} samples/s)",
            steps.len(),
            loss(first),
            first["step"],
            loss(last),
            last["step"],
            samples as f64 / seconds.max(1e-9)
        );
    }
    if let Ok(text) = std::fs::read_to_string(train.join("train.txt")) {
        for line in text.lines().rev().take(2).collect::<Vec<_>>().into_iter().rev() {
            let _ = writeln!(page, "- {}", line.trim());
        }
    }
    page.push('\n');
}

fn eval_section(page: &mut String, dir: &Path) {
    let Some(e) = read_json(&dir.join("eval").join("eval.json")) else { return };
    let m = &e["mean"];
    let scenes = e["scenes"].as_array().map_or(0, Vec::len);
    let _ = writeln!(
        page,
        "## Evaluation\n\n{scenes} held-out scenes ({} precision, {} {} steps): PSNR {:.2} dB, SSIM {:.4}, Chamfer {:.4e} (the ground truth's own halves: {:.4e})\n",
        e["precision"].as_str().unwrap_or("?"),
        e["sampler"].as_str().unwrap_or("?"),
        e["steps"],
        m["psnr"].as_f64().unwrap_or(f64::NAN),
        m["ssim"].as_f64().unwrap_or(f64::NAN),
        m["chamfer"].as_f64().unwrap_or(f64::NAN),
        m["chamfer_gt_halves"].as_f64().unwrap_or(f64::NAN),
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn test_output_is_summed_over_its_result_lines() {
        let text = "running 3 tests\ntest a::x ... ok\ntest a::y ... FAILED\nvelox: validation error VUID-1: bad\n\
                    test result: FAILED. 1 passed; 1 failed; 2 ignored; 0 measured; 0 filtered out\n\
                    test result: ok. 5 passed; 0 failed; 0 ignored; 0 measured; 3 filtered out; finished in 1s\n";
        let run = parse_tests(text);
        assert_eq!(
            run,
            TestRun {
                passed: 6,
                failed: 1,
                ignored: 2,
                failures: vec!["a::y".into()],
                validation_errors: 1,
                finished: true
            }
        );
        assert!(!parse_tests("running 3 tests\ntest a::x ... ok\n").finished);
    }
}
