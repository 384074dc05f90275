//! `log.jsonl`: one JSON object per optimiser step, appended as the step ends:
//!
//! ```text
//! {"step": 12, "seconds": 5.1, "samples": ["scene_00001"],
//!  "loss": {"total": 0.41, "surface": 0.38, "image": 0.03, "tokens": 1e-6},
//!  "grad_norm": 0.9, "lr": 0.0042,
//!  "time": {"data": 0.001, "compute": 0.35, "all_reduce": 0.0, "optimiser": 0.004}}
//! ```
//!
//! An f16 run adds `loss_scale` (the step's) and, after an overflow, `overflows` (the tries
//! of the step that were skipped).
//!
//! `seconds` counts from the start of the run, earlier parts of a resumed run included;
//! `samples` names the step's samples slot by slot (see [`super::order`]); `loss` holds the
//! model's loss terms, means over the step's batch, the total first; `time` the seconds of the
//! step by part (see [`super::trainer::TimeSplit`]). A resumed run keeps the lines up to its
//! checkpoint's step and writes the rest again.

use std::fs::File;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use serde::de::{MapAccess, Visitor};
use serde::ser::SerializeMap;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use velox_engine::{Error, Result};

use super::trainer::TimeSplit;
use velox_io::write_bytes;

/// Named values kept in their order (a JSON object whose keys are written in that order).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Terms(pub Vec<(String, f64)>);

impl Terms {
    /// The value called `name`.
    pub fn get(&self, name: &str) -> Option<f64> {
        self.0.iter().find(|t| t.0 == name).map(|t| t.1)
    }
}

impl Serialize for Terms {
    fn serialize<S: Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        let mut map = s.serialize_map(Some(self.0.len()))?;
        for (k, v) in &self.0 {
            map.serialize_entry(k, v)?;
        }
        map.end()
    }
}

impl<'de> Deserialize<'de> for Terms {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Terms, D::Error> {
        struct InOrder;
        impl<'de> Visitor<'de> for InOrder {
            type Value = Terms;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("an object of numbers")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> std::result::Result<Terms, A::Error> {
                let mut terms = Vec::new();
                while let Some(entry) = map.next_entry::<String, f64>()? {
                    terms.push(entry);
                }
                Ok(Terms(terms))
            }
        }
        d.deserialize_map(InOrder)
    }
}

/// One line of `log.jsonl`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LogLine {
    pub step: u64,
    pub seconds: f64,
    pub samples: Vec<String>,
    pub loss: Terms,
    pub grad_norm: f64,
    pub lr: f64,
    pub time: TimeSplit,
    /// f16 training: the loss scale of the step, and how many tries at a higher scale
    /// overflowed before it (each skipped and redone at half the scale).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_scale: Option<f64>,
    #[serde(default, skip_serializing_if = "is_zero")]
    pub overflows: u32,
}

fn is_zero(n: &u32) -> bool {
    *n == 0
}

/// A run's log, open for appending.
pub struct Log {
    path: PathBuf,
    file: File,
    /// The step and loss terms of each line of this layout: what the plot draws.
    history: Vec<(u64, Terms)>,
    seconds: f64,
}

impl Log {
    /// Opens the log of a run whose parameters are at `step`: the lines of steps up to `step`
    /// are kept (the file is rewritten with them, atomically), later ones dropped, and new
    /// lines are appended. A line of another layout (an older run's) is kept in the file but
    /// not plotted.
    pub fn open(path: &Path, step: u64) -> Result<Log> {
        let text = std::fs::read_to_string(path).unwrap_or_default();
        let mut kept = String::new();
        let mut history = Vec::new();
        let mut seconds = 0.0;
        for l in text.lines() {
            let Ok(value) = serde_json::from_str::<serde_json::Value>(l) else { continue };
            if value["step"].as_u64().is_none_or(|s| s > step) {
                continue;
            }
            kept += l;
            kept.push('\n');
            seconds = value["seconds"].as_f64().unwrap_or(seconds);
            // Parsed from the text, not the value, whose map would sort the terms.
            if let Ok(line) = serde_json::from_str::<LogLine>(l) {
                history.push((line.step, line.loss));
            }
        }
        write_bytes(path, kept.as_bytes())?;
        let file = std::fs::OpenOptions::new()
            .append(true)
            .open(path)
            .map_err(|e| Error::Io(format!("cannot open {} to append to it: {e}", path.display())))?;
        Ok(Log { path: path.to_path_buf(), file, history, seconds })
    }

    /// Appends a line.
    pub fn append(&mut self, line: LogLine) -> Result<()> {
        let text = serde_json::to_string(&line).expect("plain data serialises");
        writeln!(self.file, "{text}")
            .map_err(|e| Error::Io(format!("cannot write {}: {e}", self.path.display())))?;
        self.seconds = line.seconds;
        self.history.push((line.step, line.loss));
        Ok(())
    }

    /// The step and loss terms of every line of this layout, kept and appended.
    pub fn history(&self) -> &[(u64, Terms)] {
        &self.history
    }

    /// The `seconds` of the last line (0 for an empty log): where a resumed run's clock starts.
    pub fn seconds(&self) -> f64 {
        self.seconds
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(step: u64) -> LogLine {
        LogLine {
            step,
            seconds: step as f64,
            samples: vec![format!("s{step}")],
            loss: Terms(vec![("total".into(), 1.0 / step as f64), ("b".into(), 0.5), ("a".into(), 0.25)]),
            grad_norm: 2.0,
            lr: 1e-3,
            time: TimeSplit { data: 0.5, compute: 1.5, ..Default::default() },
            loss_scale: None,
            overflows: 0,
        }
    }

    #[test]
    fn a_reopened_log_keeps_the_steps_up_to_the_checkpoint_in_their_order() {
        let dir = std::env::temp_dir().join(format!("velox-log-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("log.jsonl");
        let mut log = Log::open(&path, 0).unwrap();
        for s in 1..=5 {
            log.append(line(s)).unwrap();
        }
        let text = std::fs::read_to_string(&path).unwrap();
        // The terms keep the model's order, not the alphabet's.
        assert!(text.lines().next().unwrap().contains(r#""loss":{"total":1.0,"b":0.5,"a":0.25}"#), "{text}");
        // A line of an older layout before them is kept, not plotted.
        std::fs::write(&path, format!("{{\"step\":0,\"seconds\":0.5,\"total\":3}}\n{text}not json\n"))
            .unwrap();
        let log = Log::open(&path, 3).unwrap();
        let want: Vec<(u64, Terms)> = (1..=3).map(|s| (s, line(s).loss)).collect();
        assert_eq!(log.history(), want.as_slice());
        assert_eq!(log.seconds(), 3.0);
        let kept = std::fs::read_to_string(&path).unwrap();
        assert_eq!(kept.lines().count(), 4, "{kept}");
        assert!(kept.starts_with("{\"step\":0,"), "{kept}");
        std::fs::remove_dir_all(&dir).ok();
    }
}
