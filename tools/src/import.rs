//! `velox import rgbd DIR --out VIDEO`: an RGBD capture (a depth camera's or a phone's colour
//! and depth frames with their intrinsics) made into the tracker's video folder by
//! `velox_data::capture` (its docs give the layout and the fitting into the box).

use std::path::PathBuf;

use velox_data::capture::{import_rgbd, CaptureOptions};

use crate::CliResult;

#[derive(clap::Subcommand)]
pub enum ImportCommand {
    /// An RGBD capture: DIR/intrinsics.json ({"fx", "fy", "cx", "cy", "width", "height"}),
    /// DIR/rgb/ (or color/) colour frames (PNG or JPEG) and DIR/depth/ depth frames (16-bit
    /// PNG in --depth-scale metres, or EXR in metres), as many, in name order. Writes the
    /// video `velox track --video` and `velox encode --source video` read: 24 frames spread
    /// over the clip, fitted into the scene's box, with capture.json (the frames taken, and how
    /// the box maps back to metres).
    Rgbd(RgbdArgs),
}

#[derive(clap::Args)]
pub struct RgbdArgs {
    /// The capture's folder.
    dir: PathBuf,
    /// The video folder to write.
    #[arg(long)]
    out: PathBuf,
    /// Metres per unit of a 16-bit depth PNG (0.001: millimetres, as phones and most depth
    /// cameras store them).
    #[arg(long, default_value_t = 0.001)]
    depth_scale: f64,
    /// Depths beyond this many metres are the background: dropped before the fit.
    #[arg(long)]
    max_depth: Option<f64>,
    /// Cut the clip into videos of 24 consecutive frames overlapping by this many frames
    /// (OUT/window_000, ...; 4 when given without a number) instead of resampling it to 24.
    #[arg(long, value_name = "OVERLAP", num_args = 0..=1, default_missing_value = "4")]
    windows: Option<usize>,
    /// The capture's frame rate: capture.json then gives each frame's time.
    #[arg(long)]
    fps: Option<f64>,
}

pub fn run(cmd: ImportCommand) -> CliResult<()> {
    match cmd {
        ImportCommand::Rgbd(a) => {
            let options = CaptureOptions {
                depth_scale: a.depth_scale,
                max_depth: a.max_depth,
                windows: a.windows,
                fps: a.fps,
            };
            let r = import_rgbd(&a.dir, &a.out, &options)?;
            let dropped = if r.dropped_beyond_max_depth > 0 {
                format!(", {} beyond --max-depth dropped", r.dropped_beyond_max_depth)
            } else {
                String::new()
            };
            let first = a.out.join(&r.windows[0].dir);
            println!(
                "wrote {} video(s) of {} ({} frames, {} depth pixels{dropped}) to {}: 1 m is {:.3} scene units \
                 (capture.json); track one with `velox track --video {}`",
                r.windows.len(),
                a.dir.display(),
                r.source_frames,
                r.depth_pixels,
                a.out.display(),
                r.scale,
                first.display()
            );
            Ok(())
        }
    }
}
