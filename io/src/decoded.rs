//! `decode.json`, which `velox decode` (and the demo) writes beside the per-frame files it
//! decodes: which checkpoint decoded which cloud, how, and each frame's file. `velox view`
//! reads it for the scene whose truth and cameras it shows beside the frames.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use velox_engine::Result;

use crate::{read_json, write_json};

/// The report's file name in a decode output folder.
pub const FILE: &str = "decode.json";

/// What a decoding wrote.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DecodeReport {
    /// `decode points` or `decode gaussians`.
    pub command: String,
    pub checkpoint: String,
    /// The cloud decoded: a scene folder or a PLY.
    pub cloud: String,
    pub config: String,
    pub precision: String,
    pub input_points: usize,
    /// Where the Gaussian decoder's voxels came from (`predicted`, `surface`, `input`), for
    /// Gaussians.
    pub voxels: Option<String>,
    pub sampler: String,
    pub steps: usize,
    pub points: usize,
    pub encode_seconds: f64,
    pub frames: Vec<DecodedFrame>,
}

/// One frame's file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DecodedFrame {
    pub frame: usize,
    pub tau: f32,
    /// The file's name, in the report's folder.
    pub file: String,
    /// Points (decode points) or Gaussians (decode gaussians) in the file.
    pub count: usize,
    /// Occupied voxels the Gaussians were decoded from (decode gaussians).
    pub voxels: Option<usize>,
    pub seconds: f64,
}

impl DecodeReport {
    /// Writes `dir/decode.json` and returns its path.
    pub fn write(&self, dir: &Path) -> Result<PathBuf> {
        write_json(dir.join(FILE), self)
    }

    /// Reads `dir/decode.json`.
    pub fn read(dir: &Path) -> Result<DecodeReport> {
        read_json(&dir.join(FILE))
    }

    /// The scene folder the cloud was, when it is one (it holds `cameras.json`).
    pub fn scene(&self) -> Option<PathBuf> {
        crate::scene_folder(&self.cloud)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_report_reads_back_as_written() {
        let dir = std::env::temp_dir().join(format!("velox-decoded-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let report = DecodeReport {
            command: "decode gaussians".into(),
            checkpoint: "run/checkpoint.safetensors".into(),
            cloud: dir.display().to_string(),
            config: "tiny".into(),
            precision: "f32".into(),
            input_points: 1000,
            voxels: Some("surface".into()),
            sampler: "heun".into(),
            steps: 8,
            points: 2048,
            encode_seconds: 0.25,
            frames: vec![DecodedFrame {
                frame: 3,
                tau: 0.03,
                file: "gaussians_f03.ply".into(),
                count: 77,
                voxels: Some(12),
                seconds: 0.5,
            }],
        };
        report.write(&dir).unwrap();
        assert_eq!(DecodeReport::read(&dir).unwrap(), report);
        assert_eq!(report.scene(), None, "no cameras.json: not a scene");
        std::fs::write(dir.join(FILE), "{\"command\": 3}").unwrap();
        let e = DecodeReport::read(&dir).unwrap_err().to_string();
        assert!(e.contains("decode.json") && e.contains("invalid type"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
