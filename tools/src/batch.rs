//! Batches of glTF files for `velox data gltf`: the file list (files, folders searched
//! recursively, list files), imports on several threads a few files ahead of the scene being
//! rendered, and the batch's report.
//!
//! The scenes do not depend on the number of threads: a file's scene name and seed follow from
//! its place in the list, and its import from the file alone.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Condvar, Mutex};

use serde::Serialize;
use velox_data::gltf_import::{self, Imported};

use crate::CliResult;

/// Whether `path` names a glTF file (.gltf or .glb, in any case).
fn is_gltf(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("gltf") || e.eq_ignore_ascii_case("glb"))
}

/// The glTF files under `dir`, at any depth, in name order.
fn walk(dir: &Path, out: &mut Vec<PathBuf>) -> CliResult<()> {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| format!("{}: {e}", dir.display()))?
        .map(|e| e.map(|e| e.path()).map_err(|e| format!("{}: {e}", dir.display())))
        .collect::<Result<_, _>>()?;
    entries.sort();
    for p in entries {
        if p.is_dir() {
            walk(&p, out)?;
        } else if is_gltf(&p) {
            out.push(p);
        }
    }
    Ok(())
}

/// The files to import: each of `inputs` (a file as given; a folder, its glTF files at any
/// depth in name order), then those `list` names (one per line, relative to the list's
/// folder; blank lines and `#` comments skipped), in that order.
pub fn gltf_files(inputs: &[PathBuf], list: Option<&Path>) -> CliResult<Vec<PathBuf>> {
    let mut named: Vec<PathBuf> = inputs.to_vec();
    if let Some(list) = list {
        let text = std::fs::read_to_string(list).map_err(|e| format!("{}: {e}", list.display()))?;
        let base = list.parent().unwrap_or(Path::new("."));
        named.extend(
            text.lines()
                .map(str::trim)
                .filter(|l| !l.is_empty() && !l.starts_with('#'))
                .map(|l| base.join(l)),
        );
    }
    if named.is_empty() {
        return Err("give glTF files or folders to import (or --list FILE)".into());
    }
    let mut files = Vec::new();
    for p in named {
        if p.is_dir() {
            let before = files.len();
            walk(&p, &mut files)?;
            if files.len() == before {
                eprintln!("note: {} holds no .gltf or .glb file", p.display());
            }
        } else if p.exists() {
            files.push(p);
        } else {
            return Err(format!("{}: no such file or folder", p.display()).into());
        }
    }
    if files.is_empty() {
        return Err("no .gltf or .glb file to import".into());
    }
    Ok(files)
}

/// Where file `i`'s import arrives (taken once).
type Slot = Mutex<Option<mpsc::Receiver<Result<Imported, String>>>>;

/// Imports running on worker threads, at most `2 * workers` files ahead of the one taken.
#[derive(Clone)]
pub struct Imports {
    results: Arc<Vec<Slot>>,
    taken: Arc<(Mutex<usize>, Condvar)>,
}

impl Imports {
    /// Starts importing `files` (animation `animation` of each) on `workers` threads.
    pub fn start(files: Vec<PathBuf>, animation: Option<usize>, workers: usize) -> Imports {
        let (senders, receivers): (Vec<_>, Vec<_>) = (0..files.len()).map(|_| mpsc::sync_channel(1)).unzip();
        let imports = Imports {
            results: Arc::new(receivers.into_iter().map(|r| Mutex::new(Some(r))).collect()),
            taken: Arc::new((Mutex::new(0), Condvar::new())),
        };
        let next = Arc::new(AtomicUsize::new(0));
        let (files, senders) = (Arc::new(files), Arc::new(senders));
        let ahead = 2 * workers.max(1);
        for _ in 0..workers.max(1).min(files.len()) {
            let (files, senders, next, taken) =
                (files.clone(), senders.clone(), next.clone(), imports.taken.clone());
            std::thread::spawn(move || loop {
                let i = next.fetch_add(1, Ordering::SeqCst);
                if i >= files.len() {
                    return;
                }
                // Wait until the scenes before catch up, so memory holds a few imports.
                let (lock, turned) = &*taken;
                let mut t = lock.lock().unwrap_or_else(|e| e.into_inner());
                while i >= *t + ahead {
                    t = turned.wait(t).unwrap_or_else(|e| e.into_inner());
                }
                drop(t);
                let result = gltf_import::import(&files[i], animation).map_err(|e| e.to_string());
                // The receiver is gone only when the command has stopped.
                let _ = senders[i].send(result);
            });
        }
        imports
    }

    /// The import of file `k` (each taken once, in order), waiting for it.
    pub fn take(&self, k: usize) -> CliResult<Imported> {
        let receiver = self.results[k].lock().unwrap_or_else(|e| e.into_inner()).take().expect("taken once");
        let result = receiver.recv().map_err(|_| "an import thread stopped".to_string())?;
        let (lock, turned) = &*self.taken;
        *lock.lock().unwrap_or_else(|e| e.into_inner()) = k + 1;
        turned.notify_all();
        Ok(result?)
    }
}

/// One file of a batch in its report.
#[derive(Serialize)]
pub struct Entry {
    pub file: String,
    pub scene: String,
    /// "written", "kept" (by an earlier run) or "failed".
    pub status: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    pub warnings: Vec<String>,
}

/// Writes `OUT/report.json`: the counts, the time and every file's entry, in the order of
/// `order` (the scenes' names in the order of their files).
pub fn write_report(
    out: &Path,
    mut entries: Vec<Entry>,
    order: &[String],
    seconds: f64,
) -> CliResult<PathBuf> {
    let place: std::collections::HashMap<&str, usize> =
        order.iter().enumerate().map(|(i, n)| (n.as_str(), i)).collect();
    entries.sort_by_key(|e| place.get(e.scene.as_str()).copied().unwrap_or(usize::MAX));
    let count = |s: &str| entries.iter().filter(|e| e.status == s).count();
    let report = serde_json::json!({
        "files": entries.len(),
        "written": count("written"),
        "kept": count("kept"),
        "failed": count("failed"),
        "seconds": seconds,
        "entries": entries,
    });
    let path = out.join("report.json");
    velox_io::write_bytes(&path, serde_json::to_string_pretty(&report)?.as_bytes())?;
    Ok(path)
}
