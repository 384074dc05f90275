//! RGBD captures of the world (a depth camera, a phone's LiDAR) made into the project's RGBD
//! video (`crate::rgbd`: 24 colour and depth frames of one camera, the world the scene's
//! [-1, 1]^3 box), which `velox track` and `velox encode --source video` read.
//!
//! A capture is a folder of:
//! - `intrinsics.json`: `{"fx", "fy", "cx", "cy", "width", "height"}`, pixels of an image of
//!   `width` x `height` (the colour's or the depth's: they are scaled to the depth's size);
//! - `rgb/` (or `color/`): the colour frames, PNG or JPEG, in name order;
//! - `depth/`: as many depth frames, in name order: 16-bit PNG (units of `depth_scale` metres,
//!   millimetres by default; 0 where there is no depth) or EXR (one channel of metres).
//!
//! The camera must stay still (the tracker's video has one camera). The clip is resampled to 24
//! frames spread evenly over it (the first and the last kept; it needs 24 or more), or, with
//! `windows`, cut into videos of 24 consecutive frames that overlap by that many frames (the
//! last one ending on the clip's last frame), `window_000/`, `window_001/`, ..., fitted into
//! the box together, so a long clip keeps its frame rate. Depths
//! beyond `max_depth` are dropped (the background of a capture of an object). The points the
//! depth of the 24 frames back-projects to are fitted into [-1, 1]^3: centred on their bounding
//! box and scaled so that its longest side spans 95 % of the box. The folder written holds the
//! video (at the depth's resolution, the colour resized to it) and `capture.json`: the source
//! frames taken, and the centre and scale that map the box back to the capture's metres
//! (`metres = centre + scene / scale`, in the camera's frame).
//!
//! Tests: `tests/data/capture.rs`, `python/tests`.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::procedural::FRAMES;
use crate::{DataError, DataResult};

/// How much of the box the capture's longest side spans.
pub const FILL: f32 = 0.95;

/// How a capture is read.
#[derive(Clone, Debug)]
pub struct CaptureOptions {
    /// Metres per unit of a 16-bit depth PNG.
    pub depth_scale: f64,
    /// Depths beyond this many metres are no surface (`None`: every depth counts).
    pub max_depth: Option<f64>,
    /// Cut the clip into windows of 24 consecutive frames overlapping by this many (below 24)
    /// instead of resampling it to 24.
    pub windows: Option<usize>,
    /// The capture's frame rate, when known: the record then gives each frame's time.
    pub fps: Option<f64>,
}

impl Default for CaptureOptions {
    fn default() -> CaptureOptions {
        CaptureOptions { depth_scale: 0.001, max_depth: None, windows: None, fps: None }
    }
}

#[derive(Deserialize)]
struct Intrinsics {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    width: u32,
    height: u32,
}

/// One video an import wrote.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CaptureWindow {
    /// Its folder, relative to the import's (`.` for a resampled clip).
    pub dir: String,
    /// The capture's frame index of each of its 24 frames, their files, and their times in
    /// seconds when the capture's frame rate is known.
    pub frames: Vec<usize>,
    pub colour_files: Vec<String>,
    pub depth_files: Vec<String>,
    pub times: Option<Vec<f64>>,
}

/// What an import records beside the video (`capture.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CaptureRecord {
    /// The capture's folder.
    pub source: String,
    /// Frames of the capture, and its frame rate when given.
    pub source_frames: usize,
    pub fps: Option<f64>,
    /// The videos written: one resampled clip, or the windows.
    pub windows: Vec<CaptureWindow>,
    /// The box's centre in the camera's frame, metres, and the scale from metres to the box.
    pub centre: [f64; 3],
    pub scale: f64,
    /// Pixels with a depth over the 24 frames, and those dropped beyond `max_depth`.
    pub depth_pixels: usize,
    pub dropped_beyond_max_depth: usize,
}

fn invalid(path: &Path, why: impl std::fmt::Display) -> DataError {
    DataError::Invalid(format!("{}: {why}", path.display()))
}

/// The image files of `dir` with one of `extensions`, in name order.
fn frame_files(dir: &Path, extensions: &[&str]) -> DataResult<Vec<PathBuf>> {
    let entries =
        std::fs::read_dir(dir).map_err(|e| DataError::Io(format!("cannot read {}: {e}", dir.display())))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .and_then(|x| x.to_str())
                    .is_some_and(|x| extensions.contains(&x.to_lowercase().as_str()))
        })
        .collect();
    files.sort();
    Ok(files)
}

/// A depth frame in metres, `[h, w]` row-major, with its size.
fn read_depth(path: &Path, depth_scale: f64) -> DataResult<(Vec<f32>, u32, u32)> {
    let is_exr = path.extension().is_some_and(|x| x.eq_ignore_ascii_case("exr"));
    if is_exr {
        return Ok(velox_io::image::read_exr_depth(path)?);
    }
    let img = image::open(path).map_err(|e| invalid(path, e))?;
    let image::DynamicImage::ImageLuma16(depth) = img else {
        return Err(invalid(
            path,
            format!(
                "a depth PNG must be 16-bit greyscale (units of {depth_scale} m), this one is {:?}",
                img.color()
            ),
        ));
    };
    let (w, h) = depth.dimensions();
    Ok((depth.pixels().map(|p| (p[0] as f64 * depth_scale) as f32).collect(), w, h))
}

/// A colour frame resized to `w` x `h`, RGB in [0, 1].
fn read_colour(path: &Path, w: u32, h: u32) -> DataResult<Vec<f32>> {
    let img = image::open(path).map_err(|e| invalid(path, e))?.to_rgb8();
    let img = if img.dimensions() == (w, h) {
        img
    } else {
        image::imageops::resize(&img, w, h, image::imageops::FilterType::Triangle)
    };
    Ok(img.pixels().flat_map(|p| p.0.map(|c| c as f32 / 255.0)).collect())
}

/// `count` indices spread evenly over `n` (the first and the last included); the first alone
/// for one. How a clip is resampled to the frames a model reads (here, and the generators'
/// condition frames).
pub fn spread(n: usize, count: usize) -> Vec<usize> {
    if count <= 1 {
        return vec![0];
    }
    (0..count).map(|i| (i * (n - 1) + (count - 1) / 2) / (count - 1)).collect()
}

/// Imports the capture in `dir` into the video folder `out` (see the module docs).
pub fn import_rgbd(dir: &Path, out: &Path, options: &CaptureOptions) -> DataResult<CaptureRecord> {
    if !(options.depth_scale.is_finite() && options.depth_scale > 0.0) {
        return Err(DataError::Invalid(format!("depth scale {} must be positive", options.depth_scale)));
    }
    if let Some(m) = options.max_depth.filter(|m| !(m.is_finite() && *m > 0.0)) {
        return Err(DataError::Invalid(format!("max depth {m} must be positive")));
    }
    if let Some(o) = options.windows.filter(|&o| o >= FRAMES) {
        return Err(DataError::Invalid(format!(
            "windows overlapping by {o} frames: the overlap must be below {FRAMES}"
        )));
    }
    if let Some(r) = options.fps.filter(|r| !(r.is_finite() && *r > 0.0)) {
        return Err(DataError::Invalid(format!("frame rate {r} must be positive")));
    }
    let k_path = dir.join("intrinsics.json");
    let k: Intrinsics = crate::format::read_json(&k_path)?;
    let sound = [k.fx, k.fy].iter().all(|v| v.is_finite() && *v > 0.0)
        && [k.cx, k.cy].iter().all(|v| v.is_finite())
        && k.width > 0
        && k.height > 0;
    if !sound {
        return Err(invalid(
            &k_path,
            "fx and fy must be positive, cx and cy finite, width and height non-zero",
        ));
    }
    let colour_dir = ["rgb", "color", "colour"].iter().map(|d| dir.join(d)).find(|d| d.is_dir());
    let colour_dir = colour_dir.ok_or_else(|| invalid(dir, "no rgb/ (or color/) folder of colour frames"))?;
    let colours = frame_files(&colour_dir, &["png", "jpg", "jpeg"])?;
    let depths = frame_files(&dir.join("depth"), &["png", "exr"])?;
    if colours.len() != depths.len() {
        return Err(invalid(
            dir,
            format!(
                "{} colour frames and {} depth frames: one depth a colour frame",
                colours.len(),
                depths.len()
            ),
        ));
    }
    if colours.len() < FRAMES {
        return Err(invalid(
            dir,
            format!("{} frames: the video takes {FRAMES}, spread over 24 or more", colours.len()),
        ));
    }
    let windows: Vec<Vec<usize>> = match options.windows {
        None => vec![spread(colours.len(), FRAMES)],
        Some(overlap) => {
            window_starts(colours.len(), overlap).into_iter().map(|s| (s..s + FRAMES).collect()).collect()
        }
    };
    let mut used: Vec<usize> = windows.iter().flatten().copied().collect();
    used.sort_unstable();
    used.dedup();
    let mut depth = std::collections::BTreeMap::new();
    let mut size = None;
    let (mut pixels, mut dropped) = (0, 0);
    for &f in &used {
        let (mut z, w, h) = read_depth(&depths[f], options.depth_scale)?;
        if *size.get_or_insert((w, h)) != (w, h) {
            return Err(invalid(
                &depths[f],
                format!("{w} x {h} pixels, the first depth frame has {:?}", size),
            ));
        }
        for (i, d) in z.iter_mut().enumerate() {
            if !(d.is_finite() && *d >= 0.0) {
                return Err(invalid(
                    &depths[f],
                    format!("pixel ({}, {}) has depth {d}", i as u32 % w, i as u32 / w),
                ));
            }
            if *d > 0.0 {
                pixels += 1;
                if options.max_depth.is_some_and(|m| *d as f64 > m) {
                    *d = 0.0;
                    dropped += 1;
                }
            }
        }
        depth.insert(f, z);
    }
    let (w, h) = size.expect("24 frames");
    // The intrinsics at the depth's resolution.
    let (sx, sy) = (w as f64 / k.width as f64, h as f64 / k.height as f64);
    let (fx, fy, cx, cy) = (k.fx * sx, k.fy * sy, k.cx * sx, k.cy * sy);
    // The bounding box of every back-projected point, in the camera's frame (metres).
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for z in depth.values() {
        for (i, &d) in z.iter().enumerate().filter(|(_, d)| **d > 0.0) {
            let (u, v) = ((i as u32 % w) as f64 + 0.5, (i as u32 / w) as f64 + 0.5);
            let d = d as f64;
            let p = [(u - cx) / fx * d, (v - cy) / fy * d, d];
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
    }
    if lo[0] > hi[0] {
        return Err(invalid(dir, "no pixel of the frames taken has a depth (within the max depth)"));
    }
    let centre: [f64; 3] = std::array::from_fn(|a| (lo[a] + hi[a]) / 2.0);
    let half = (0..3).map(|a| (hi[a] - lo[a]) / 2.0).fold(0.0, f64::max).max(1e-9);
    let scale = FILL as f64 / half;
    let camera = Camera {
        width: w,
        height: h,
        fx: fx as f32,
        fy: fy as f32,
        cx: cx as f32,
        cy: cy as f32,
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: centre.map(|c| (c * scale) as f32),
    };
    let name = |p: &PathBuf| p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let mut written = Vec::with_capacity(windows.len());
    for (k, frames) in windows.into_iter().enumerate() {
        let sub = if options.windows.is_some() { format!("window_{k:03}") } else { ".".to_string() };
        let folder = if options.windows.is_some() { out.join(&sub) } else { out.to_path_buf() };
        std::fs::create_dir_all(&folder)
            .map_err(|e| DataError::Io(format!("cannot create {}: {e}", folder.display())))?;
        for (i, &f) in frames.iter().enumerate() {
            let rgb = read_colour(&colours[f], w, h)?;
            velox_io::image::write_png(&folder.join(format!("f{i:02}.png")), &rgb, w, h)?;
            let scene_z: Vec<f32> = depth[&f].iter().map(|&d| (d as f64 * scale) as f32).collect();
            velox_io::image::write_exr_depth(&folder.join(format!("f{i:02}_depth.exr")), &scene_z, w, h)?;
        }
        velox_io::write_bytes(&folder.join("camera.json"), pretty(&camera).as_bytes())?;
        // Each video must read back as the tracker reads it, every point inside the box.
        let video = crate::rgbd::read_video_folder(&folder)?;
        crate::rgbd::rgbd_cloud(&video, crate::rgbd::DEFAULT_POINTS, 0)?;
        written.push(CaptureWindow {
            dir: sub,
            colour_files: frames.iter().map(|&f| name(&colours[f])).collect(),
            depth_files: frames.iter().map(|&f| name(&depths[f])).collect(),
            times: options.fps.map(|r| frames.iter().map(|&f| f as f64 / r).collect()),
            frames,
        });
    }
    let record = CaptureRecord {
        source: dir.display().to_string(),
        source_frames: colours.len(),
        fps: options.fps,
        windows: written,
        centre,
        scale,
        depth_pixels: pixels,
        dropped_beyond_max_depth: dropped,
    };
    velox_io::write_bytes(&out.join("capture.json"), pretty(&record).as_bytes())?;
    Ok(record)
}

/// The first frames of windows of 24 consecutive frames of a clip of `n` (24 or more) that
/// overlap by `overlap`: every `24 - overlap` frames, the last one ending on the clip's last.
pub fn window_starts(n: usize, overlap: usize) -> Vec<usize> {
    let step = FRAMES - overlap.min(FRAMES - 1);
    let mut starts: Vec<usize> = (0..).map(|k| k * step).take_while(|&s| s + FRAMES <= n).collect();
    if starts.last().is_some_and(|&s| s + FRAMES < n) {
        starts.push(n - FRAMES);
    }
    starts
}

/// Pretty JSON of plain data.
fn pretty<T: Serialize>(v: &T) -> String {
    serde_json::to_string_pretty(v).expect("plain data serialises")
}
