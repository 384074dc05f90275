//! The clip's conventions and the names of per-frame files, defined once for every crate.
//!
//! A clip is [`FRAMES`] frames; frame f has the time tau = f / 100 ([`tau_of`]), the time the
//! data, the encoder's 4D points and every decoder take. Per-frame outputs are named
//! `PREFIX_fFF.ply` ([`frame_file`]: `gaussians_f07.ply`, `points_f07.ply`, `tracks_f07.ply`);
//! other tools' numbered sequences end their names in the frame's number (`frame_0007.ply`,
//! [`numbered_frame`]), which is also how [`sequence_file`] names the sequences Velox exports.

use std::path::{Path, PathBuf};

use velox_engine::{Error, Result};

use crate::read_error;

/// Frames of a clip: the models' window.
pub const FRAMES: usize = 24;

/// The frame time of frame `frame`: tau = frame / 100.
pub fn tau_of(frame: usize) -> f32 {
    frame as f32 / 100.0
}

/// The frame a frame time belongs to: the nearest, clamped to the clip.
pub fn frame_of_tau(tau: f32) -> usize {
    ((tau * 100.0).round() as usize).min(FRAMES - 1)
}

/// The file of frame `frame` of a per-frame output: `PREFIX_fFF.ply`.
pub fn frame_file(prefix: &str, frame: usize) -> String {
    frame_file_as(prefix, frame, "ply")
}

/// [`frame_file`] with another extension: `PREFIX_fFF.EXT`.
pub fn frame_file_as(prefix: &str, frame: usize, ext: &str) -> String {
    format!("{prefix}_f{frame:02}.{ext}")
}

/// The frame in a file name `PREFIX_fFF.ply`, if it is one.
pub fn frame_of_file(name: &str, prefix: &str) -> Option<usize> {
    name.strip_prefix(prefix)?.strip_prefix("_f")?.strip_suffix(".ply")?.parse().ok()
}

/// Frame `frame` of an exported sequence: `frame_0007.EXT`, the numbered names SuperSplat and
/// other players load as a sequence in name order.
pub fn sequence_file(frame: usize, ext: &str) -> String {
    format!("frame_{frame:04}.{ext}")
}

/// Another tool's numbered frame, `PREFIX<digits>.ply` (`frame_0007.ply`, `000123.ply`): the
/// prefix and the number.
pub fn numbered_frame(name: &str) -> Option<(&str, usize)> {
    let stem = name.strip_suffix(".ply")?;
    let digits = stem.bytes().rev().take_while(u8::is_ascii_digit).count();
    let (prefix, number) = stem.split_at(stem.len() - digits);
    Some((prefix, number.parse().ok()?))
}

/// The per-frame PLYs of `dir` named `PREFIX_fFF.ply`, in frame order.
pub fn frame_files(dir: &Path, prefix: &str) -> Result<Vec<(usize, PathBuf)>> {
    let mut list: Vec<(usize, PathBuf)> =
        names(dir)?.into_iter().filter_map(|(n, p)| frame_of_file(&n, prefix).map(|f| (f, p))).collect();
    list.sort();
    Ok(list)
}

/// The numbered PLYs of `dir` (another tool's sequence), in number order: they must share one
/// prefix, and no two may be the same frame.
pub fn numbered_files(dir: &Path) -> Result<Vec<(usize, PathBuf)>> {
    let names = names(dir)?;
    let numbered: Vec<(&str, usize, &PathBuf)> =
        names.iter().filter_map(|(n, p)| numbered_frame(n).map(|(prefix, f)| (prefix, f, p))).collect();
    if let Some(other) = numbered.iter().find(|(prefix, ..)| *prefix != numbered[0].0) {
        return Err(Error::Invalid(format!(
            "{}: numbered PLYs of two sequences, {} and {}: give the folder of one",
            dir.display(),
            file_name(numbered[0].2),
            file_name(other.2)
        )));
    }
    let mut list: Vec<(usize, PathBuf)> = numbered.into_iter().map(|(_, f, p)| (f, p.clone())).collect();
    list.sort();
    if let Some(w) = list.windows(2).find(|w| w[0].0 == w[1].0) {
        return Err(Error::Invalid(format!(
            "{} and {} are both frame {}",
            w[0].1.display(),
            w[1].1.display(),
            w[0].0
        )));
    }
    Ok(list)
}

fn file_name(p: &Path) -> String {
    p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
}

/// The entries of `dir`, name and path, in name order.
fn names(dir: &Path) -> Result<Vec<(String, PathBuf)>> {
    let entries = std::fs::read_dir(dir).map_err(|e| read_error(dir, e))?;
    let mut files: Vec<(String, PathBuf)> = entries
        .filter_map(|e| e.ok())
        .map(|e| (e.file_name().to_string_lossy().into_owned(), e.path()))
        .collect();
    files.sort();
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_and_format() {
        assert_eq!(frame_file("gaussians", 7), "gaussians_f07.ply");
        assert_eq!(frame_of_file("gaussians_f07.ply", "gaussians"), Some(7));
        assert_eq!(frame_of_file("points_f07.ply", "gaussians"), None);
        assert_eq!(frame_of_file("gaussians_fxx.ply", "gaussians"), None);
        assert_eq!(sequence_file(7, "ply"), "frame_0007.ply");
        assert_eq!(numbered_frame("frame_0007.ply"), Some(("frame_", 7)));
        assert_eq!(numbered_frame("000123.ply"), Some(("", 123)));
        assert_eq!(numbered_frame("point_cloud.ply"), None);
        assert_eq!(numbered_frame("frame_7.png"), None);
        for f in 0..FRAMES {
            assert_eq!(frame_of_tau(tau_of(f)), f);
        }
        assert_eq!(frame_of_tau(1.0), FRAMES - 1);
    }
}
