//! Tracking points through an RGBD video, for every front end (`velox track`, the Python
//! package): the video back-projected to a 4D cloud, the autoencoder's encoder turning it into
//! tokens, the tracker following each query from the first frame, and where the video shows
//! each tracked point (the depth test the data uses; not learned).
//!
//! Tests: `tools/tests/models_cli.rs` (`velox track`), `python/tests`.

use std::path::Path;

use velox_data::rgbd::{self, RgbdVideo};
use velox_data::{DataError, DataResult};
use velox_engine::Tensor;
use velox_io::cloud;
use velox_models::velox::autoencoder::{Autoencoder, FRAMES};
use velox_models::velox::tracker::{Track, Tracker};

/// The video of `dir`: a scene's (its `video/` and the video camera of `cameras.json`) when it
/// has `cameras.json`, else a video folder's (`fFF.png`, `fFF_depth.exr`, `camera.json`).
pub fn read_video(dir: &Path) -> DataResult<RgbdVideo> {
    if dir.join("cameras.json").is_file() {
        rgbd::read_scene_video(dir)
    } else {
        rgbd::read_video_folder(dir)
    }
}

/// The pixels of a `grid` x `grid` lattice of the first frame that show surface,
/// back-projected: the default queries.
pub fn grid_queries(video: &RgbdVideo, grid: usize) -> Vec<[f32; 3]> {
    let cam = &video.camera;
    let mut out = Vec::new();
    for j in 0..grid {
        for i in 0..grid {
            let u = ((i as f32 + 0.5) * cam.width as f32 / grid as f32).floor();
            let v = ((j as f32 + 0.5) * cam.height as f32 / grid as f32).floor();
            let z = video.depth[0][v as usize * cam.width as usize + u as usize];
            if z > 0.0 {
                out.push(cam.unproject(u + 0.5, v + 0.5, z).map(|x| x.clamp(-1.0, 1.0)));
            }
        }
    }
    out
}

/// Tracks of queries through a video.
pub struct Tracked {
    /// Per query, its position at every frame (scene units).
    pub tracks: Vec<Track>,
    /// Per query and frame, whether the video shows the point there.
    pub visible: Vec<[bool; FRAMES]>,
    /// Points of the back-projected cloud the tokens encode.
    pub cloud_points: usize,
}

/// Follows `queries` (points on the first frame) through `video` with `tracker` on the tokens
/// `ae` makes of the video's back-projected cloud (at most `points` points, drawn, like the
/// encoder's queries, from `seed`). `tracker` must have learned `ae`'s tokens (checked by the
/// caller with `Tracker::check_encoder`, which needs the autoencoder's file).
pub fn track(
    ae: &Autoencoder,
    tracker: &Tracker,
    video: &RgbdVideo,
    queries: &[[f32; 3]],
    points: usize,
    seed: u64,
) -> DataResult<Tracked> {
    if queries.is_empty() {
        return Err(DataError::Invalid("no query points to track".into()));
    }
    if let Some(q) = queries.iter().find(|q| q.iter().any(|v| !v.is_finite())) {
        return Err(DataError::Invalid(format!("query {q:?} is not a finite point")));
    }
    let gpu = ae.store.flat_params().gpu();
    let cloud_points = rgbd::rgbd_cloud(video, points, seed)?;
    let k = ae.cfg.encoder.tokens;
    if cloud_points.len() < k {
        return Err(DataError::Invalid(format!(
            "the video shows {} surface pixels over its frames; the encoder needs at least {k}",
            cloud_points.len()
        )));
    }
    let flat: Vec<f32> = cloud_points.iter().flatten().copied().collect();
    let (tokens, picked) = ae.encode_with_queries(&cloud::upload(gpu, &flat)?, seed)?;
    let token_points = cloud::query_points(&flat, &picked.read::<u32>()?);
    let token_points = Tensor::from_slice(gpu, &[k, 4], &token_points)?;
    let first_colours = rgbd::colours_at(&video.rgb[0], &video.camera, queries);
    let tracks = tracker.predict(&tokens, &token_points, queries, &first_colours)?;
    let cam = &video.camera;
    let visible = tracks.iter().map(|t| std::array::from_fn(|f| cam.sees(t[f], &video.depth[f]))).collect();
    Ok(Tracked { tracks, visible, cloud_points: cloud_points.len() })
}

/// A window of a clip: its video, and the capture's frame of each of its frames.
pub type Window = (RgbdVideo, Vec<usize>);

/// Tracks of queries through a clip cut into overlapping windows (`velox import rgbd
/// --windows`), one track per query over every frame the windows cover.
pub struct StitchedTracks {
    /// The capture's frame of each frame of the tracks, in order.
    pub frames: Vec<usize>,
    /// Per query, its position at each of `frames`; and whether the video shows it there.
    pub tracks: Vec<Vec<[f32; 3]>>,
    pub visible: Vec<Vec<bool>>,
}

/// For each window of a clip (the capture's frame of each of its frames, as [`read_windows`]
/// gives them), how many of its first frames the windows before it cover already: the frames
/// after those are its own. Each window must be 24 consecutive frames, start inside the frames
/// covered before it and end after them. What [`track_windows`] and `velox decode` stitch by.
pub fn window_shares(windows: &[&[usize]]) -> DataResult<Vec<usize>> {
    let mut shares = Vec::with_capacity(windows.len());
    let mut covered: Option<(usize, usize)> = None;
    for frames in windows {
        if frames.len() != FRAMES || frames.windows(2).any(|w| w[1] != w[0] + 1) {
            return Err(DataError::Invalid(format!(
                "a window's frames {frames:?} are not {FRAMES} consecutive frames"
            )));
        }
        let (start, end) = (frames[0], frames[FRAMES - 1]);
        let shared = match covered {
            None => 0,
            Some((first, last)) if (first..=last).contains(&start) && end > last => last + 1 - start,
            Some((_, last)) if end <= last => {
                return Err(DataError::Invalid(format!(
                "the window from frame {start} ends on {end}, inside the one before (which ends on {last})"
            )))
            }
            Some((_, last)) => {
                return Err(DataError::Invalid(format!(
                "the window from frame {start} does not start inside the one before (which ends on {last})"
            )))
            }
        };
        shares.push(shared);
        covered = Some((covered.map_or(start, |c| c.0), end));
    }
    Ok(shares)
}

/// Follows `queries` (on the first window's first frame) through `windows` (each video with
/// the capture's frame of each of its frames, as [`window_shares`] takes them): each window
/// after the first is tracked from where the one before puts the queries on its first frame,
/// and takes over from the frame after the last one the windows share. Every window is encoded
/// and tracked as [`track`] does it.
pub fn track_windows(
    ae: &Autoencoder,
    tracker: &Tracker,
    windows: &[Window],
    queries: &[[f32; 3]],
    points: usize,
    seed: u64,
) -> DataResult<StitchedTracks> {
    let frames: Vec<&[usize]> = windows.iter().map(|w| &w.1[..]).collect();
    let shares = window_shares(&frames)?;
    let Some(((first_video, first_frames), rest)) = windows.split_first() else {
        return Err(DataError::Invalid("no window to track".into()));
    };
    let first = track(ae, tracker, first_video, queries, points, seed)?;
    let mut out = StitchedTracks {
        frames: first_frames.clone(),
        tracks: first.tracks.iter().map(|t| t.to_vec()).collect(),
        visible: first.visible.iter().map(|v| v.to_vec()).collect(),
    };
    for ((video, frames), &shared) in rest.iter().zip(&shares[1..]) {
        // Where the queries stand on this window's first frame.
        let at = frames[0] - out.frames[0];
        let from: Vec<[f32; 3]> = out.tracks.iter().map(|t| t[at]).collect();
        let next = track(ae, tracker, video, &from, points, seed)?;
        out.frames.extend_from_slice(&frames[shared..]);
        for (q, (t, v)) in next.tracks.iter().zip(&next.visible).enumerate() {
            out.tracks[q].extend_from_slice(&t[shared..]);
            out.visible[q].extend_from_slice(&v[shared..]);
        }
    }
    Ok(out)
}

/// The windows of a capture imported with `--windows` (its `capture.json`), read as the
/// tracker reads them; `None` when `dir` is not such an import.
pub fn read_windows(dir: &Path) -> DataResult<Option<Vec<Window>>> {
    let path = dir.join("capture.json");
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path)
        .map_err(|e| DataError::Io(format!("cannot read {}: {e}", path.display())))?;
    let record: velox_data::capture::CaptureRecord = serde_json::from_str(&text)
        .map_err(|e| DataError::Invalid(format!("{}: not an import's record: {e}", path.display())))?;
    if record.windows.iter().all(|w| w.dir == ".") {
        return Ok(None);
    }
    record
        .windows
        .into_iter()
        .map(|w| Ok((rgbd::read_video_folder(&dir.join(&w.dir))?, w.frames)))
        .collect::<DataResult<Vec<_>>>()
        .map(Some)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_share_the_frames_the_ones_before_cover() {
        let w = |first: usize| (first..first + FRAMES).collect::<Vec<usize>>();
        let (a, b, c) = (w(0), w(16), w(30));
        assert_eq!(window_shares(&[&a, &b, &c]).unwrap(), [0, 8, 10]);
        assert_eq!(window_shares(&[&a]).unwrap(), [0]);
        let err = |ws: &[&[usize]]| window_shares(ws).unwrap_err().to_string();
        assert!(
            err(&[&a, &c]).contains("from frame 30 does not start inside the one before (which ends on 23)")
        );
        assert!(err(&[&a, &b, &w(10)]).contains("ends on 33, inside the one before (which ends on 39)"));
        assert!(err(&[&a, &a[..10]]).contains("are not 24 consecutive frames"));
        let skipping: Vec<usize> = (0..FRAMES).map(|f| 2 * f).collect();
        assert!(err(&[&skipping]).contains("are not 24 consecutive frames"));
    }
}
