//! `velox track`: 3D tracks of query points through an RGBD video. The video (a scene's
//! `video/` or a folder of `fFF.png`, `fFF_depth.exr` and `camera.json`, `velox_data::rgbd`)
//! is back-projected to a 4D cloud, the autoencoder's encoder turns it into tokens, and the
//! tracker follows each query from the first frame. Writes into `--out`:
//!
//! - `tracks.json`: the inputs, and per query its position at every frame (scene units) and
//!   whether the video shows it there (the depth test the data uses; not learned);
//! - `tracks_fFF.ply`: per frame, every query's point (float x y z, uchar red green blue in
//!   the query's colour, uchar visible);
//! - `overlay/fFF.png`: the video's frames with each track's path drawn so far, faded where
//!   the point is hidden, and the same as the animated `overlay.gif`.

use std::path::{Path, PathBuf};

use velox_engine::Gpu;
use velox_io::image::{write_gif, write_png};
use velox_io::tracks::{TrackReport, TrackedQuery};
use velox_io::write_bytes;
use velox_models::velox::autoencoder::{Autoencoder, FRAMES};
use velox_models::velox::tracker::{Track, Tracker};
use velox_models::Model;

use velox_tasks::track::{grid_queries, read_video};

use crate::overlay::{colours, draw_tracks};
use crate::CliResult;

#[derive(clap::Args)]
pub struct TrackArgs {
    /// The RGBD video: a scene folder (its video/ and the video camera of cameras.json), or a
    /// folder of f00.png..f23.png, f00_depth.exr..f23_depth.exr and camera.json.
    #[arg(long)]
    video: PathBuf,
    /// Autoencoder checkpoint whose encoder makes the tokens (the one the tracker trained on).
    #[arg(long)]
    autoencoder: PathBuf,
    /// Tracker checkpoint (`velox train tracker`).
    #[arg(long)]
    checkpoint: PathBuf,
    /// Query points: a JSON file of [x, y, z] points on the first frame (scene units) [default:
    /// a grid of --grid x --grid pixels of the first frame, those showing surface,
    /// back-projected].
    #[arg(long)]
    queries: Option<PathBuf>,
    /// Side of the pixel grid the default queries come from.
    #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u64).range(1..=1024))]
    grid: u64,
    /// Output folder.
    #[arg(long, default_value = "velox-track")]
    out: PathBuf,
    /// Seed of the back-projected cloud's draw and the encoder's queries.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Most points of the back-projected cloud.
    #[arg(long, default_value_t = velox_data::rgbd::DEFAULT_POINTS as u64, value_parser = clap::value_parser!(u64).range(1..=16_777_216))]
    points: u64,
}

/// Queries from a JSON file of [x, y, z] points.
fn read_queries(path: &Path) -> CliResult<Vec<[f32; 3]>> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let q: Vec<[f32; 3]> = serde_json::from_str(&text)
        .map_err(|e| format!("{}: not a JSON list of [x, y, z] points: {e}", path.display()))?;
    if q.is_empty() {
        return Err(format!("{}: no query points", path.display()).into());
    }
    Ok(q)
}

/// The PLY of one frame's points: float x y z, uchar red green blue visible.
fn frame_ply(points: &[[f32; 3]], colours: &[[f32; 3]], visible: &[bool]) -> Vec<u8> {
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\ncomment velox tracks, one frame\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\n\
         property uchar blue\nproperty uchar visible\nend_header\n",
        points.len()
    )
    .into_bytes();
    for ((p, c), &v) in points.iter().zip(colours).zip(visible) {
        for x in p {
            bytes.extend_from_slice(&x.to_le_bytes());
        }
        bytes.extend(c.map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8));
        bytes.push(v as u8);
    }
    bytes
}

pub fn run(a: &TrackArgs) -> CliResult<()> {
    let gpu = Gpu::new()?;
    // A capture imported in windows (`velox import rgbd --windows`) is one clip of them all.
    let windows = match velox_tasks::track::read_windows(&a.video)? {
        Some(w) => w,
        None => vec![(read_video(&a.video)?, (0..FRAMES).collect())],
    };
    let tracker = Tracker::load(&gpu, &a.checkpoint)?;
    tracker.check_encoder(&a.autoencoder)?;
    let ae = Autoencoder::load(&gpu, &a.autoencoder)?;
    let queries = match &a.queries {
        Some(path) => read_queries(path)?,
        None => grid_queries(&windows[0].0, a.grid as usize),
    };
    if queries.is_empty() {
        return Err(format!(
            "no pixel of a {0} x {0} grid on the first frame of {1} shows surface: pass --queries or a finer --grid",
            a.grid,
            a.video.display()
        )
        .into());
    }
    println!(
        "tracking {} queries through {}{} with the {} tracker on {}",
        queries.len(),
        a.video.display(),
        if windows.len() > 1 { format!(" ({} windows)", windows.len()) } else { String::new() },
        tracker.cfg.name,
        gpu.caps().name
    );
    let stitched =
        velox_tasks::track::track_windows(&ae, &tracker, &windows, &queries, a.points as usize, a.seed)?;
    let clip_frames = stitched.frames.len();
    // Each frame of the clip from the first window that holds it (as the stitching takes it),
    // drawn with the tracks of that window's 24 frames.
    let index_of =
        |source: usize| stitched.frames.iter().position(|&f| f == source).expect("a tracked frame");
    let window_tracks = |k: usize| -> (Vec<Track>, Vec<[bool; FRAMES]>) {
        let at: Vec<usize> = windows[k].1.iter().map(|&f| index_of(f)).collect();
        let tracks = stitched.tracks.iter().map(|t| std::array::from_fn(|j| t[at[j]])).collect();
        let hidden = stitched.visible.iter().map(|v| std::array::from_fn(|j| !v[at[j]])).collect();
        (tracks, hidden)
    };
    let cam = windows[0].0.camera;
    let overlay = a.out.join("overlay");
    std::fs::create_dir_all(&overlay).map_err(|e| format!("creating {}: {e}", overlay.display()))?;
    let colour = colours(&window_tracks(0).0, &cam);
    let mut clip = Vec::with_capacity(clip_frames);
    let mut drawn = vec![false; clip_frames];
    for (k, (video, frames)) in windows.iter().enumerate() {
        let (tracks, hidden) = window_tracks(k);
        for (j, &source) in frames.iter().enumerate() {
            let i = index_of(source);
            if std::mem::replace(&mut drawn[i], true) {
                continue;
            }
            let positions: Vec<[f32; 3]> = tracks.iter().map(|t| t[j]).collect();
            let visible: Vec<bool> = hidden.iter().map(|h| !h[j]).collect();
            write_bytes(
                &a.out.join(velox_io::frames::frame_file("tracks", i)),
                &frame_ply(&positions, &colour, &visible),
            )?;
            let mut rgb = video.rgb[j].clone();
            draw_tracks(&mut rgb, &cam, &tracks, &hidden, &colour, j);
            write_png(&overlay.join(format!("f{i:02}.png")), &rgb, cam.width, cam.height)?;
            clip.push(rgb);
        }
    }
    write_gif(&a.out.join("overlay.gif"), &clip, cam.width, cam.height, 100)?;
    let report = TrackReport {
        // Absolute, so that the viewer finds the scene from any folder.
        video: std::path::absolute(&a.video).unwrap_or_else(|_| a.video.clone()).display().to_string(),
        autoencoder: a.autoencoder.display().to_string(),
        checkpoint: a.checkpoint.display().to_string(),
        frames: clip_frames,
        source_frames: stitched.frames.clone(),
        queries: queries
            .iter()
            .zip(&stitched.tracks)
            .zip(&stitched.visible)
            .map(|((q, t), v)| TrackedQuery { query: *q, positions: t.clone(), visible: v.clone() })
            .collect(),
    };
    let written = report.write(&a.out)?;
    let shown = stitched.visible.iter().flatten().filter(|&&v| v).count();
    println!(
        "wrote {} (tracks of {} queries, visible at {:.0} % of their frames), {clip_frames} PLY files and the \
         overlay frames under {} (and as overlay.gif)",
        written.display(),
        queries.len(),
        100.0 * shown as f64 / (queries.len() * clip_frames) as f64,
        overlay.display()
    );
    Ok(())
}
