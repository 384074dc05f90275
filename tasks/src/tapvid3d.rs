//! TAPVid-3D's own files scored as the benchmark's evaluation scores them
//! (`tapnet/tapvid3d/evaluation/evaluate_model.py`): a clip's ground truth is an `.npz` of
//! `tracks_XYZ` [T, N, 3] (camera frame), `visibility` [T, N], `queries_xyt` [N, 3] (x, y and
//! the query's frame), `fx_fy_cx_cy` [4] and `images_jpeg_bytes` (the video, whose size sets
//! the thresholds' pixels); a tracker's predictions are an `.npz` of the same name with
//! `tracks_XYZ` [T, N, 3] and `visibility` [T, N]. The metrics are
//! `velox_models::eval::tracking`'s, each query's own frame read by the scalings that need it;
//! a video's figure is the mean over its clips. So Velox's evaluator scores any tracker.
//!
//! Checked against the benchmark's `compute_tapvid3d_metrics` on random clips with random query
//! frames: AJ, APD and OA agree to 12 digits in the median, mean, none, per_trajectory,
//! reproduce_2d and median_on_queries scalings (its per_trajectory and local_neighborhood
//! branches take batched query points; `evaluate_model.py` passes them unbatched, where they
//! raise and the clip scores zero: here they are scored).
//!
//! Tests: `python/tests` (files written by numpy's `savez` and `savez_compressed`).

use std::path::Path;

use velox_data::{DataError, DataResult};
use velox_io::npz::{self, Array, Npz};
use velox_models::eval::tracking::{benchmark_focal, CameraTracks, Scaling, TrackingMetrics};

/// A clip's ground truth, track-major.
#[derive(Clone, Debug)]
pub struct Clip {
    pub frames: usize,
    pub tracks: usize,
    /// `positions[t * frames + f]`: track t at frame f.
    pub positions: Vec<[f64; 3]>,
    pub visible: Vec<bool>,
    /// Each track's query frame.
    pub query_frames: Vec<usize>,
    /// fx, fy, cx, cy in the video's pixels.
    pub intrinsics: [f64; 4],
    /// The video's width and height.
    pub size: (u32, u32),
}

fn invalid(path: &Path, why: impl std::fmt::Display) -> DataError {
    DataError::Invalid(format!("{}: {why}", path.display()))
}

/// `name` of the archive, of shape `shape` (`None`: any size there).
fn array<'a>(path: &Path, npz: &'a Npz, name: &str, shape: &[Option<usize>]) -> DataResult<&'a Array> {
    let a = npz.get(name).ok_or_else(|| {
        let names: Vec<&str> = npz.keys().map(String::as_str).collect();
        invalid(path, format!("no {name} array (it holds {})", names.join(", ")))
    })?;
    let fits =
        a.shape.len() == shape.len() && a.shape.iter().zip(shape).all(|(&g, s)| s.is_none_or(|s| s == g));
    if !fits {
        let want: Vec<String> = shape.iter().map(|s| s.map_or("N".into(), |n| n.to_string())).collect();
        return Err(invalid(path, format!("{name} has shape {:?}, expected [{}]", a.shape, want.join(", "))));
    }
    Ok(a)
}

fn numbers(path: &Path, name: &str, a: &Array) -> DataResult<Vec<f64>> {
    let v = a.to_f64().ok_or_else(|| invalid(path, format!("{name} holds objects, not numbers")))?;
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        return Err(invalid(path, format!("{name} holds {} at index {i}", v[i])));
    }
    Ok(v)
}

/// Time-major [T, N, 3] to track-major positions.
fn track_major(v: &[f64], frames: usize, tracks: usize) -> Vec<[f64; 3]> {
    (0..tracks * frames)
        .map(|k| {
            let (t, f) = (k / frames, k % frames);
            let i = (f * tracks + t) * 3;
            [v[i], v[i + 1], v[i + 2]]
        })
        .collect()
}

/// Time-major [T, N] to track-major flags.
fn track_major_flags(v: &[bool], frames: usize, tracks: usize) -> Vec<bool> {
    (0..tracks * frames).map(|k| v[(k % frames) * tracks + k / frames]).collect()
}

/// The ground truth of a clip of the benchmark.
pub fn read_clip(path: &Path) -> DataResult<Clip> {
    let npz = npz::read(path)?;
    let xyz = array(path, &npz, "tracks_XYZ", &[None, None, Some(3)])?;
    let (frames, tracks) = (xyz.shape[0], xyz.shape[1]);
    if frames == 0 || tracks == 0 {
        return Err(invalid(path, format!("tracks_XYZ of shape {:?} holds no track", xyz.shape)));
    }
    let positions = track_major(&numbers(path, "tracks_XYZ", xyz)?, frames, tracks);
    let vis = array(path, &npz, "visibility", &[Some(frames), Some(tracks)])?;
    let visible = track_major_flags(
        &vis.to_bool().ok_or_else(|| invalid(path, "visibility holds objects"))?,
        frames,
        tracks,
    );
    let queries = numbers(path, "queries_xyt", array(path, &npz, "queries_xyt", &[Some(tracks), Some(3)])?)?;
    let query_frames = queries
        .chunks(3)
        .enumerate()
        .map(|(i, q)| {
            let f = q[2].round();
            if f < 0.0 || f >= frames as f64 {
                return Err(invalid(path, format!("query {i} is on frame {}, of a clip of {frames}", q[2])));
            }
            Ok(f as usize)
        })
        .collect::<DataResult<Vec<_>>>()?;
    let k = numbers(path, "fx_fy_cx_cy", array(path, &npz, "fx_fy_cx_cy", &[Some(4)])?)?;
    if k[0] <= 0.0 || k[1] <= 0.0 {
        return Err(invalid(path, format!("fx_fy_cx_cy {k:?}: the focal lengths must be positive")));
    }
    let images = npz
        .get("images_jpeg_bytes")
        .ok_or_else(|| invalid(path, "no images_jpeg_bytes, whose size sets the pixels of the thresholds"))?;
    let size = match &images.values {
        npz::Values::Object(bytes) => npz::first_jpeg_size(bytes),
        npz::Values::Int(v) if images.dtype.ends_with("u1") => {
            npz::first_jpeg_size(&v.iter().map(|&b| b as u8).collect::<Vec<u8>>())
        }
        _ => None,
    }
    .ok_or_else(|| invalid(path, "images_jpeg_bytes holds no JPEG whose size can be read"))?;
    Ok(Clip { frames, tracks, positions, visible, query_frames, intrinsics: [k[0], k[1], k[2], k[3]], size })
}

/// A tracker's predictions for `clip`: track-major positions and visibility.
pub fn read_predictions(path: &Path, clip: &Clip) -> DataResult<(Vec<[f64; 3]>, Vec<bool>)> {
    let npz = npz::read(path)?;
    let (t, n) = (clip.frames, clip.tracks);
    let xyz = numbers(path, "tracks_XYZ", array(path, &npz, "tracks_XYZ", &[Some(t), Some(n), Some(3)])?)?;
    let vis = array(path, &npz, "visibility", &[Some(t), Some(n)])?;
    let vis = vis.to_bool().ok_or_else(|| invalid(path, "visibility holds objects"))?;
    Ok((track_major(&xyz, t, n), track_major_flags(&vis, t, n)))
}

/// The benchmark's metrics of `predicted` against `clip` under `scaling`.
pub fn score(
    clip: &Clip,
    predicted: &(Vec<[f64; 3]>, Vec<bool>),
    scaling: Scaling,
) -> velox_engine::Result<TrackingMetrics> {
    let hidden = |v: &[bool]| -> Vec<bool> { v.iter().map(|&s| !s).collect() };
    let (truth_hidden, pred_hidden) = (hidden(&clip.visible), hidden(&predicted.1));
    let (fx, fy) = benchmark_focal(clip.intrinsics[0], clip.intrinsics[1], clip.size.0, clip.size.1);
    TrackingMetrics::of_queries(
        CameraTracks { positions: &clip.positions, occluded: &truth_hidden },
        CameraTracks { positions: &predicted.0, occluded: &pred_hidden },
        clip.frames,
        &clip.query_frames,
        fx,
        fy,
        scaling,
    )
}

/// The metrics of every clip (`ground_truth[i]` against `predictions[i]`) under each of
/// `scalings`: per clip, then their mean per scaling.
pub fn evaluate(
    ground_truth: &[&Path],
    predictions: &[&Path],
    scalings: &[Scaling],
    each: &mut dyn FnMut(&Path, &[TrackingMetrics]),
) -> DataResult<Vec<TrackingMetrics>> {
    if ground_truth.len() != predictions.len() || ground_truth.is_empty() {
        return Err(DataError::Invalid(format!(
            "{} ground-truth files and {} prediction files: one prediction a clip",
            ground_truth.len(),
            predictions.len()
        )));
    }
    let mut all: Vec<Vec<TrackingMetrics>> = vec![Vec::new(); scalings.len()];
    for (gt, pred) in ground_truth.iter().zip(predictions) {
        let clip = read_clip(gt)?;
        let predicted = read_predictions(pred, &clip)?;
        let metrics = scalings
            .iter()
            .map(|&s| score(&clip, &predicted, s).map_err(|e| invalid(gt, e)))
            .collect::<DataResult<Vec<_>>>()?;
        each(gt, &metrics);
        for (slot, m) in all.iter_mut().zip(metrics) {
            slot.push(m);
        }
    }
    Ok(all.iter().map(|m| TrackingMetrics::mean(m)).collect())
}
