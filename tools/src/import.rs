//! `velox import rgbd DIR --out VIDEO`: an RGBD capture (a depth camera's or a phone's colour
//! and depth frames with their intrinsics) made into the tracker's video folder by
//! `velox_data::capture` (its docs give the layout and the fitting into the box).
//! `velox import video FILE --out DIR`: a video file's frames, through ffmpeg
//! (`velox_data::video`), as a folder of frames or, with a depth video, the tracker's video.

use std::path::PathBuf;

use velox_data::capture::{import_rgbd, CaptureOptions, CaptureRecord};
use velox_data::video::{import_video, VideoOptions};

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
    /// A video file (any container and codec ffmpeg reads; ffmpeg must be on PATH). Colour
    /// alone: its frames as OUT/frame_00000.png, ..., the condition `velox generate --video`
    /// takes. With --depth (a 16-bit grey video frame for frame with it, stored losslessly:
    /// FFV1 in Matroska, say) and --intrinsics or --fov: an RGBD capture in OUT/capture/,
    /// imported as `import rgbd` does into the tracker's video in OUT.
    Video(VideoArgs),
}

#[derive(clap::Args)]
pub struct VideoArgs {
    /// The video file.
    file: PathBuf,
    /// The folder to write (new or empty).
    #[arg(long)]
    out: PathBuf,
    /// The depth video, in --depth-scale metres a unit (0: no depth).
    #[arg(long)]
    depth: Option<PathBuf>,
    /// The camera's intrinsics: {"fx", "fy", "cx", "cy", "width", "height"} in pixels.
    #[arg(long)]
    intrinsics: Option<PathBuf>,
    /// Or the camera's vertical field of view in degrees (the principal point at the centre).
    #[arg(long)]
    fov: Option<f64>,
    /// Resample the clip to this many frames a second (default: every frame of the file).
    #[arg(long)]
    fps: Option<f64>,
    #[command(flatten)]
    capture: CaptureArgs,
}

/// How a capture's depth is read and its clip cut (`import rgbd`, and `import video` with a
/// depth video).
#[derive(clap::Args)]
pub struct CaptureArgs {
    /// Metres per unit of a 16-bit depth PNG or depth video (0.001: millimetres, as phones and
    /// most depth cameras store them).
    #[arg(long, default_value_t = 0.001)]
    depth_scale: f64,
    /// Depths beyond this many metres are the background: dropped before the fit.
    #[arg(long)]
    max_depth: Option<f64>,
    /// Cut the clip into videos of 24 consecutive frames overlapping by this many frames
    /// (OUT/window_000, ...; 4 when given without a number) instead of resampling it to 24.
    #[arg(long, value_name = "OVERLAP", num_args = 0..=1, default_missing_value = "4")]
    windows: Option<usize>,
}

impl CaptureArgs {
    fn options(&self, fps: Option<f64>) -> CaptureOptions {
        CaptureOptions {
            depth_scale: self.depth_scale,
            max_depth: self.max_depth,
            windows: self.windows,
            fps,
        }
    }
}

#[derive(clap::Args)]
pub struct RgbdArgs {
    /// The capture's folder.
    dir: PathBuf,
    /// The video folder to write.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    capture: CaptureArgs,
    /// The capture's frame rate: capture.json then gives each frame's time.
    #[arg(long)]
    fps: Option<f64>,
}

/// Says what an RGBD import wrote.
fn report(r: &CaptureRecord, source: &std::path::Path, out: &std::path::Path) {
    let dropped = if r.dropped_beyond_max_depth > 0 {
        format!(", {} beyond --max-depth dropped", r.dropped_beyond_max_depth)
    } else {
        String::new()
    };
    println!(
        "wrote {} video(s) of {} ({} frames, {} depth pixels{dropped}) to {}: 1 m is {:.3} scene units \
         (capture.json); track the whole clip with `velox track --video {}`, decode it with \
         `velox decode gaussians --cloud {}`",
        r.windows.len(),
        source.display(),
        r.source_frames,
        r.depth_pixels,
        out.display(),
        r.scale,
        out.display(),
        out.display()
    );
}

pub fn run(cmd: ImportCommand) -> CliResult<()> {
    match cmd {
        ImportCommand::Rgbd(a) => {
            let r = import_rgbd(&a.dir, &a.out, &a.capture.options(a.fps))?;
            report(&r, &a.dir, &a.out);
            Ok(())
        }
        ImportCommand::Video(a) => {
            let options = VideoOptions {
                depth: a.depth.clone(),
                intrinsics: a.intrinsics.clone(),
                fov_y: a.fov,
                fps: a.fps,
                capture: a.capture.options(None),
            };
            println!("decoding {} through ffmpeg", a.file.display());
            let r = import_video(&a.file, &a.out, &options)?;
            let rate = r.fps.map(|f| format!(" at {f:.3} fps")).unwrap_or_default();
            println!("{} frames of {} x {}{rate} in {}", r.frames, r.width, r.height, r.frames_dir.display());
            match &r.capture {
                Some(capture) => report(capture, &a.file, &a.out),
                None => println!(
                    "no depth: the frames condition `velox generate --video {}`; give --depth to track or encode it",
                    a.out.display()
                ),
            }
            Ok(())
        }
    }
}
