//! Video files in: a clip of any container and codec ffmpeg reads, decoded through the
//! `ffmpeg` and `ffprobe` programs on PATH (Debian's package `ffmpeg`).
//!
//! - Colour alone: the frames are written to the output folder as `frame_00000.png`, ...: a
//!   folder of frames, which `velox generate --video` takes as its condition.
//! - With a depth video (16-bit grey, stored losslessly: FFV1 in Matroska, say, in units of
//!   `depth_scale` metres, 0 where there is no depth) and the camera's intrinsics (a JSON file
//!   as [`crate::capture`] reads it, or a vertical field of view with the principal point at
//!   the centre): the frames become an RGBD capture in `OUT/capture/` (`rgb/`, `depth/`,
//!   `intrinsics.json`), imported by [`crate::capture::import_rgbd`] into the tracker's video
//!   in OUT (resampled to 24 frames or cut into windows), ready for `velox track` and
//!   `velox encode --source video`.
//!
//! The clip's frame rate (ffprobe's) is recorded with the frames, or the rate it is resampled
//! to (`fps`). Tests: `tests/data/capture.rs`.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::capture::{import_rgbd, CaptureOptions, CaptureRecord};
use crate::{DataError, DataResult};

/// How a video is imported.
#[derive(Clone, Debug, Default)]
pub struct VideoOptions {
    /// The depth video, frame for frame with the colour one.
    pub depth: Option<PathBuf>,
    /// The intrinsics JSON (`{"fx", "fy", "cx", "cy", "width", "height"}`).
    pub intrinsics: Option<PathBuf>,
    /// Or the vertical field of view in degrees, centred.
    pub fov_y: Option<f64>,
    /// Resample the clip to this frame rate (every frame of the file when `None`).
    pub fps: Option<f64>,
    /// How the RGBD capture is imported (its `fps` is set from the video's).
    pub capture: CaptureOptions,
}

/// What an import wrote.
#[derive(Clone, Debug)]
pub struct VideoImport {
    /// Frames decoded, their size and rate.
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub fps: Option<f64>,
    /// The colour frames (colour alone), or the capture folder (with depth).
    pub frames_dir: PathBuf,
    /// With depth: the tracker's video import.
    pub capture: Option<CaptureRecord>,
}

const MISSING: &str = "is not on PATH: velox import video decodes through ffmpeg; install it \
                       (Debian and Ubuntu: apt-get install ffmpeg; macOS: brew install ffmpeg)";

fn words(w: &[&str]) -> Vec<OsString> {
    w.iter().map(OsString::from).collect()
}

/// Runs `program` with `args`, failing with its own words when it fails.
fn run(program: &str, args: &[OsString]) -> DataResult<String> {
    let out = Command::new(program).args(args).output().map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => DataError::Invalid(format!("{program} {MISSING}")),
        _ => DataError::Io(format!("running {program}: {e}")),
    })?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let tail: Vec<&str> = err.lines().rev().take(4).collect();
        let tail: Vec<&str> = tail.into_iter().rev().collect();
        return Err(DataError::Invalid(format!("{program} failed ({}): {}", out.status, tail.join(" / "))));
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The frame rate of the first video stream of `video` (ffprobe's `r_frame_rate`, `30000/1001`).
pub fn frame_rate(video: &Path) -> DataResult<Option<f64>> {
    let mut args = words(&["-v", "error", "-select_streams", "v:0", "-show_entries", "stream=r_frame_rate"]);
    args.extend(words(&["-of", "csv=p=0"]));
    args.push(video.into());
    let text = run("ffprobe", &args)?;
    let rate = text.trim();
    if rate.is_empty() {
        return Err(DataError::Invalid(format!("{}: ffprobe finds no video stream", video.display())));
    }
    let (n, d) = rate.split_once('/').unwrap_or((rate, "1"));
    let (n, d) = (n.parse::<f64>().ok(), d.parse::<f64>().ok());
    Ok(n.zip(d).filter(|(_, d)| *d > 0.0).map(|(n, d)| n / d).filter(|r| r.is_finite() && *r > 0.0))
}

/// Decodes every frame of `video` (at `fps` when given) into `dir/frame_NNNNN.png` as
/// `pix_fmt` (rgb24, or gray16be for depth); returns how many.
fn decode_frames(video: &Path, dir: &Path, pix_fmt: &str, fps: Option<f64>) -> DataResult<usize> {
    std::fs::create_dir_all(dir).map_err(|e| DataError::Io(format!("creating {}: {e}", dir.display())))?;
    let pattern = dir.join("frame_%05d.png");
    let mut args = words(&["-v", "error", "-nostdin", "-i"]);
    args.push(video.into());
    if let Some(f) = fps {
        args.extend(words(&["-vf", &format!("fps={f}")]));
    }
    args.extend(words(&["-pix_fmt", pix_fmt, "-start_number", "0", "-f", "image2"]));
    args.push(pattern.into());
    run("ffmpeg", &args)?;
    let count = std::fs::read_dir(dir)
        .map_err(|e| DataError::Io(format!("{}: {e}", dir.display())))?
        .filter(|e| e.as_ref().is_ok_and(|e| e.file_name().to_string_lossy().starts_with("frame_")))
        .count();
    if count == 0 {
        return Err(DataError::Invalid(format!("{}: ffmpeg decoded no frame", video.display())));
    }
    Ok(count)
}

/// Imports `video` into `out`, which must be new or empty (see the module docs).
pub fn import_video(video: &Path, out: &Path, o: &VideoOptions) -> DataResult<VideoImport> {
    if !video.is_file() {
        return Err(DataError::Invalid(format!("{} is not a video file", video.display())));
    }
    if std::fs::read_dir(out).is_ok_and(|mut d| d.next().is_some()) {
        return Err(DataError::Invalid(format!("{} is not empty: give a new folder", out.display())));
    }
    if let Some(f) = o.fps.filter(|f| !(f.is_finite() && *f > 0.0)) {
        return Err(DataError::Invalid(format!("a frame rate of {f}: give a positive number")));
    }
    match (&o.depth, &o.intrinsics, o.fov_y) {
        (Some(_), None, None) => {
            return Err(DataError::Invalid(
                "a depth video needs the camera's intrinsics: give their JSON or a vertical field of view"
                    .into(),
            ))
        }
        (_, Some(_), Some(_)) => {
            return Err(DataError::Invalid("give the intrinsics or a field of view, not both".into()))
        }
        (None, Some(_), _) | (None, _, Some(_)) => {
            return Err(DataError::Invalid(
                "intrinsics are for a depth video: give the depth video too".into(),
            ))
        }
        _ => {}
    }
    if let Some(fov) = o.fov_y.filter(|f| !(*f > 0.0 && *f < 180.0)) {
        return Err(DataError::Invalid(format!("a field of view of {fov} degrees: give one in (0, 180)")));
    }
    let fps = match o.fps {
        Some(f) => Some(f),
        None => frame_rate(video)?,
    };
    let frames_dir = if o.depth.is_some() { out.join("capture") } else { out.to_path_buf() };
    let colour_dir = if o.depth.is_some() { frames_dir.join("rgb") } else { frames_dir.clone() };
    let frames = decode_frames(video, &colour_dir, "rgb24", o.fps)?;
    let first = colour_dir.join("frame_00000.png");
    let (width, height) = image::image_dimensions(&first)
        .map_err(|e| DataError::Invalid(format!("{}: {e}", first.display())))?;
    let Some(depth) = &o.depth else {
        return Ok(VideoImport { frames, width, height, fps, frames_dir, capture: None });
    };
    let depths = decode_frames(depth, &frames_dir.join("depth"), "gray16be", o.fps)?;
    if depths != frames {
        return Err(DataError::Invalid(format!(
            "{} has {frames} frames and {} has {depths}: the depth video must match the colour one frame for frame",
            video.display(),
            depth.display()
        )));
    }
    let k_path = frames_dir.join("intrinsics.json");
    let k = match (&o.intrinsics, o.fov_y) {
        (Some(path), _) => {
            std::fs::read(path).map_err(|e| DataError::Io(format!("{}: {e}", path.display())))?
        }
        (None, Some(fov)) => {
            let f = 0.5 * height as f64 / (0.5 * fov.to_radians()).tan();
            let (cx, cy) = (0.5 * width as f64, 0.5 * height as f64);
            format!(
                r#"{{"fx": {f}, "fy": {f}, "cx": {cx}, "cy": {cy}, "width": {width}, "height": {height}}}"#
            )
            .into_bytes()
        }
        (None, None) => unreachable!("checked above"),
    };
    velox_io::write_bytes(&k_path, &k)?;
    let options = CaptureOptions { fps: fps.or(o.capture.fps), ..o.capture.clone() };
    let record = import_rgbd(&frames_dir, out, &options)?;
    Ok(VideoImport { frames, width, height, fps, frames_dir, capture: Some(record) })
}
