//! `tracks.json`, which `velox track` (and Python's `Tracker.track` through it) writes: the
//! inputs, the clip's frames, and per query its position at every frame of the clip (scene
//! units) and whether the video shows it there. `velox view` reads it to draw the tracks.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use velox_engine::{Error, Result};

use crate::{parse_json, read_parsed, write_json};

/// The report's file name in a track output folder.
pub const FILE: &str = "tracks.json";

/// What a tracking wrote.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrackReport {
    /// The RGBD video tracked (a scene folder, a video folder, or an import in windows).
    pub video: String,
    pub autoencoder: String,
    pub checkpoint: String,
    /// Frames of the clip: 24, or more for a capture imported in windows.
    pub frames: usize,
    /// The capture's frame of each frame (0 to 23 for a scene's or a video folder's video).
    pub source_frames: Vec<usize>,
    pub queries: Vec<TrackedQuery>,
}

/// One query's track.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrackedQuery {
    /// Where it starts, on the first frame.
    pub query: [f32; 3],
    /// Its position at each frame.
    pub positions: Vec<[f32; 3]>,
    /// Whether the video shows it at each frame.
    pub visible: Vec<bool>,
}

impl TrackReport {
    /// Fails unless every query has a finite position and a visibility at each frame.
    pub fn check(&self) -> Result<()> {
        if self.source_frames.len() != self.frames {
            return Err(Error::Invalid(format!(
                "{} frames but {} source frames",
                self.frames,
                self.source_frames.len()
            )));
        }
        for (t, q) in self.queries.iter().enumerate() {
            let finite = q.positions.iter().flatten().all(|x| x.is_finite());
            if q.positions.len() != self.frames || q.visible.len() != self.frames || !finite {
                return Err(Error::Invalid(format!(
                    "query {t}: expected {} finite positions and visibilities, got {} and {}",
                    self.frames,
                    q.positions.len(),
                    q.visible.len()
                )));
            }
        }
        Ok(())
    }

    /// Writes `dir/tracks.json` and returns its path.
    pub fn write(&self, dir: &Path) -> Result<PathBuf> {
        self.check()?;
        write_json(dir.join(FILE), self)
    }

    /// Reads and checks `dir/tracks.json`.
    pub fn read(dir: &Path) -> Result<TrackReport> {
        read_parsed(&dir.join(FILE), |bytes| {
            let report: TrackReport = parse_json(bytes)?;
            report.check()?;
            Ok(report)
        })
    }

    /// The video folder tracked, when it is a scene folder (it holds `cameras.json`).
    pub fn scene(&self) -> Option<PathBuf> {
        crate::scene_folder(&self.video)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_report_reads_back_and_a_short_track_is_refused() {
        let dir = std::env::temp_dir().join(format!("velox-tracks-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let query = |k: f32| TrackedQuery {
            query: [k, 0.0, 0.0],
            positions: (0..30).map(|f| [k, f as f32 * 0.01, 0.0]).collect(),
            visible: (0..30).map(|f| f % 3 != 0).collect(),
        };
        let mut report = TrackReport {
            video: "video".into(),
            autoencoder: "ae.safetensors".into(),
            checkpoint: "tracker.safetensors".into(),
            frames: 30,
            source_frames: (0..30).collect(),
            queries: vec![query(0.1), query(0.2)],
        };
        report.write(&dir).unwrap();
        assert_eq!(TrackReport::read(&dir).unwrap(), report);
        report.queries[1].visible.pop();
        assert!(report.write(&dir).unwrap_err().to_string().contains("query 1: expected 30"));
        let mut json: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join(FILE)).unwrap()).unwrap();
        json["queries"][0]["positions"][3] = serde_json::json!([0.0, "x", 0.0]);
        std::fs::write(dir.join(FILE), json.to_string()).unwrap();
        let e = TrackReport::read(&dir).unwrap_err().to_string();
        assert!(e.contains("tracks.json") && e.contains("invalid type"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
