//! `velox generate`: a trained generator makes the dynamic tokens of the object a video (or an
//! image) shows; the autoencoder decodes their Gaussians frame by frame, rendered from the
//! input view and from views around the object.
//!
//! Writes to the output folder:
//! - `tokens.safetensors`: the generated tokens, `[k, token_dim]` f32 (tensor `tokens`), in the
//!   autoencoder's space (the generator's normalisation undone);
//! - `gaussians_fFF.ply` per frame (3D Gaussian splatting layout, `velox render` reads it);
//! - `input/fFF.png` (the input view) and `novel/vV_fFF.png` (views 1..N on a ring about the
//!   object, 20 degrees up, at the input camera's distance);
//! - `clip.gif`: every frame, the condition beside the input view and the first novel view;
//! - `sheet.png`: one row per view (the input video's frame first when it has one), frames
//!   0, 6, 12, 18, 23 across (the frames asked for, at most 6);
//! - `generate.json`: what was run and written.
//!
//! The input view is the scene's video camera (`--video SCENE`), a folder's `camera.json`, or
//! the data's conditioning camera at distance 3 on +x (the generator's frame puts the camera
//! there: `velox_tasks::condition`).

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;
use velox_data::camera::{ring_cameras, video_camera_at, Camera};
use velox_engine::Gpu;
use velox_io::image::{write_gif, write_png};
use velox_io::{ply, write_bytes};
use velox_models::config::GenerationTask;
use velox_models::eval::generation::rendered;
use velox_models::velox::decode::{Decoding, Sampling, VoxelSource};
use velox_models::velox::generator::GenerateSpec;
use velox_tasks::condition::read_condition;
use velox_tasks::generate::GeneratorModels;

use crate::decode::{
    name, parse_frames, progress, voxel_decoder, Frames, PrecisionArg, SamplerArg, VoxelArg,
};
use crate::CliResult;

#[derive(clap::Args)]
pub struct GenerateArgs {
    /// Generator checkpoint (`velox train generator`).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// The autoencoder whose tokens the generator learned: its Gaussian decoder decodes them.
    #[arg(long)]
    pub autoencoder: PathBuf,
    /// The video: a dataset scene (its conditioning video and camera), or a folder of PNG
    /// frames (24 of them are read, spread over the folder; a `camera.json` beside them is the
    /// input view).
    #[arg(long, conflicts_with = "image", required_unless_present = "image")]
    pub video: Option<PathBuf>,
    /// The image (image-to-4D generators): a PNG file.
    #[arg(long)]
    pub image: Option<PathBuf>,
    /// DINOv2 weights, when the generator was trained with them (the same file).
    #[arg(long, value_name = "FILE")]
    pub dinov2: Option<PathBuf>,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Integration steps of the sampler.
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u64).range(1..=10_000))]
    pub steps: u64,
    #[arg(long, value_enum, default_value_t = SamplerArg::Euler)]
    pub sampler: SamplerArg,
    /// Classifier-free guidance scale: v = v_null + s (v_video - v_null); 1 turns it off.
    #[arg(long, default_value_t = 3.0)]
    pub guidance: f32,
    /// Seed of the generator's noise (and of the surface samples of `--voxels surface`).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long, value_enum, default_value_t = PrecisionArg::F32)]
    pub precision: PrecisionArg,
    /// Frames to decode: comma-separated indices in 0..=23, or `all`.
    #[arg(long, default_value = "all", value_parser = parse_frames)]
    pub frames: Frames,
    /// Where the Gaussian decoder's voxels come from [default: predicted with --voxel-decoder,
    /// else surface]; `input` needs a scene (its point cloud).
    #[arg(long, value_enum)]
    pub voxels: Option<VoxelArg>,
    /// A voxel decoder trained on the autoencoder's tokens, for `--voxels predicted`.
    #[arg(long)]
    pub voxel_decoder: Option<PathBuf>,
    /// Views around the object besides the input view.
    #[arg(long, default_value_t = 9, value_parser = clap::value_parser!(u64).range(0..=64))]
    pub views: u64,
    /// Side of the rendered images in pixels [default: the input camera's].
    #[arg(long, value_parser = clap::value_parser!(u32).range(16..=4096))]
    pub resolution: Option<u32>,
    /// Surface points per frame for `--voxels surface`.
    #[arg(long, default_value_t = 16384, value_parser = clap::value_parser!(u64).range(1..=100_000_000))]
    pub points: u64,
}

#[derive(Serialize)]
struct Report {
    command: &'static str,
    generator: String,
    autoencoder: String,
    input: String,
    task: GenerationTask,
    dinov2: bool,
    steps: u64,
    sampler: SamplerArg,
    guidance: f32,
    seed: u64,
    voxels: VoxelSource,
    generate_seconds: f64,
    frames: Vec<FrameReport>,
    views: usize,
    sheet: String,
    /// The frames as an animated GIF: the condition, the input view, the first novel view.
    clip: String,
}

#[derive(Serialize)]
struct FrameReport {
    frame: usize,
    gaussians: String,
    count: usize,
    voxels: usize,
}

/// The condition frames of `--video` or `--image` for a generator of `task` and frame `size`,
/// and the input camera (at `resolution`, else its own).
pub fn read_input(
    video: Option<&Path>,
    image: Option<&Path>,
    task: GenerationTask,
    size: usize,
) -> CliResult<(Vec<f32>, Camera, bool)> {
    match (video, image) {
        (Some(dir), None) => {
            let scene = dir.join("meta.json").is_file();
            let pixels = read_condition(dir, task, size)?;
            let camera = if scene {
                velox_data::rgbd::scene_video_camera(dir)?
            } else if dir.join("camera.json").is_file() {
                velox_data::rgbd::read_camera(&dir.join("camera.json"))?
            } else {
                let first = velox_tasks::condition::frame_files(dir)?;
                let res = image_size(&first[0])?;
                video_camera_at(3.0, res)
            };
            Ok((pixels, camera, scene))
        }
        (None, Some(png)) => {
            if task == GenerationTask::Video {
                return Err("this generator reads videos: give --video".into());
            }
            Ok((read_condition(png, task, size)?, video_camera_at(3.0, image_size(png)?), false))
        }
        _ => Err("give --video or --image".into()),
    }
}

fn image_size(png: &Path) -> CliResult<u32> {
    let (w, h) = image::image_dimensions(png).map_err(|e| format!("{}: {e}", png.display()))?;
    Ok(w.min(h))
}

/// `cam` at another resolution (the same field of view).
pub fn resized(cam: &Camera, res: u32) -> Camera {
    let s = res as f32 / cam.width as f32;
    Camera {
        width: res,
        height: (cam.height as f32 * s).round() as u32,
        fx: cam.fx * s,
        fy: cam.fy * s,
        cx: cam.cx * s,
        cy: cam.cy * s,
        ..*cam
    }
}

/// Images of one size in a grid, `rows` of `cols`, row-major: one `[rows h, cols w, 3]` image.
pub fn grid(images: &[Vec<f32>], cols: usize, w: usize, h: usize) -> Vec<f32> {
    images.chunks(cols).flat_map(|row| crate::overlay::side_by_side(row, w, h)).collect()
}

/// Views beside the condition in a frame of `clip.gif`: the input view and the first novel one.
const CLIP_VIEWS: usize = 2;

/// Up to 6 of `frames`, spread evenly, for the contact sheet.
pub fn sheet_frames(frames: &[usize]) -> Vec<usize> {
    let n = frames.len().min(6);
    let mut picked: Vec<usize> = (0..n).map(|i| frames[i * (frames.len() - 1) / (n - 1).max(1)]).collect();
    picked.dedup();
    picked
}

/// Writes the generated tokens as `tokens.safetensors`.
fn write_tokens(path: &Path, tokens: &[f32], shape: &[usize]) -> CliResult<()> {
    let view = safetensors::tensor::TensorView::new(
        safetensors::tensor::Dtype::F32,
        shape.to_vec(),
        bytemuck::cast_slice(tokens),
    )?;
    let bytes = safetensors::serialize([("tokens", view)], None)?;
    write_bytes(path, &bytes)?;
    Ok(())
}

pub fn run(a: &GenerateArgs) -> CliResult<()> {
    let clip: Vec<usize> = (0..velox_models::velox::autoencoder::FRAMES).collect();
    let wanted = a.frames.among(&clip)?;
    let gpu = Gpu::new()?;
    let mut m = GeneratorModels::load(&gpu, &a.checkpoint, &a.autoencoder, a.dinov2.as_deref())?;
    m.ae.set_precision(a.precision.into())?;
    let cfg = m.generator.cfg.clone();
    let (pixels, input_cam, scene) =
        read_input(a.video.as_deref(), a.image.as_deref(), cfg.task, cfg.image_size)?;
    let default_voxels = if a.voxel_decoder.is_some() { VoxelArg::Predicted } else { VoxelArg::Surface };
    let source = VoxelSource::from(a.voxels.unwrap_or(default_voxels));
    let cloud = match (source, a.video.as_deref()) {
        (VoxelSource::Input, Some(dir)) if scene => Some(crate::decode::read_cloud(dir)?),
        (VoxelSource::Input, _) => {
            return Err("--voxels input needs a dataset scene as --video (its point cloud)".into())
        }
        _ => None,
    };
    let decoder = voxel_decoder(&gpu, a.voxel_decoder.as_deref(), &a.autoencoder, &[source])?;
    // A dataset scene's views are drawn on its background; any other input's on black.
    let background = match a.video.as_deref() {
        Some(dir) if scene => velox_data::format::read_meta(dir)?.background,
        _ => [0.0; 3],
    };
    std::fs::create_dir_all(a.out.join("input")).map_err(|e| format!("creating {}: {e}", a.out.display()))?;
    if a.views > 0 {
        std::fs::create_dir_all(a.out.join("novel"))
            .map_err(|e| format!("creating {}: {e}", a.out.display()))?;
    }
    let input = a.video.as_deref().or(a.image.as_deref()).expect("clap requires one");
    println!(
        "generating the {} tokens of {} with the {} generator ({} steps, {:?}, guidance {}) on {}{}",
        cfg.tokens,
        input.display(),
        cfg.name,
        a.steps,
        a.sampler,
        a.guidance,
        gpu.caps().name,
        if m.dino.is_some() { ", with DINOv2" } else { "" }
    );
    let start = Instant::now();
    let spec = GenerateSpec {
        steps: a.steps as usize,
        sampler: a.sampler.into(),
        guidance: a.guidance,
        seed: a.seed,
        precision: a.precision.into(),
    };
    let bar = progress(spec.steps, "sampler steps");
    let tokens = m.generate(&gpu, &pixels, &spec, &mut |i| bar.set_position(i as u64))?;
    bar.finish_and_clear();
    let generate_seconds = start.elapsed().as_secs_f64();
    write_tokens(&a.out.join("tokens.safetensors"), &tokens.read::<f32>()?, tokens.shape())?;
    let mut decoding = Decoding::from_tokens(&m.ae, tokens, cloud.as_deref(), a.seed)?;
    if let Some(d) = &decoder {
        decoding = decoding.with_voxel_decoder(d)?;
    }
    let res = a.resolution.unwrap_or(input_cam.width);
    let input_cam = resized(&input_cam, res);
    let r = input_cam.position().iter().map(|v| v * v).sum::<f32>().sqrt();
    let cams: Vec<Camera> =
        std::iter::once(input_cam).chain(ring_cameras(r, a.views as usize, res)).collect();
    let (w, h) = (cams[0].width as usize, cams[0].height as usize);
    let sampling = Sampling { points: a.points as usize, steps: 20, sampler: SamplerArg::Heun.into() };
    let sheet_at = sheet_frames(&wanted);
    let mut sheet: Vec<Vec<Vec<f32>>> = vec![Vec::new(); cams.len() + 1];
    let bar = progress(wanted.len(), "frames decoded and rendered");
    let mut frames = Vec::new();
    let mut clip = Vec::new();
    for &f in &wanted {
        let centres = decoding.voxels(f, source, &sampling)?;
        let g = decoding.gaussians(f, &centres)?;
        let path = a.out.join(velox_io::frames::frame_file("gaussians", f));
        let host = g.download()?;
        ply::write(&path, &host)?;
        frames.push(FrameReport {
            frame: f,
            gaussians: name(&path),
            count: host.len(),
            voxels: centres.len() / 3,
        });
        // The clip's frame: the condition beside the input view and the first novel view.
        let mut clip_row = vec![condition_frame(&pixels, cfg.task, cfg.image_size, f, w, h)];
        for (v, cam) in cams.iter().enumerate() {
            let rgb = rendered(&gpu, &g, cam, background)?;
            if v < CLIP_VIEWS {
                clip_row.push(rgb.clone());
            }
            let file = match v {
                0 => a.out.join(format!("input/f{f:02}.png")),
                v => a.out.join(format!("novel/v{v}_f{f:02}.png")),
            };
            write_png(&file, &rgb, w as u32, h as u32)?;
            if sheet_at.contains(&f) {
                sheet[v + 1].push(rgb);
            }
        }
        if sheet_at.contains(&f) {
            sheet[0].push(clip_row[0].clone());
        }
        clip.push(crate::overlay::side_by_side(&clip_row, w, h));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let cols = sheet[0].len();
    let images: Vec<Vec<f32>> = sheet.into_iter().flatten().collect();
    let k = (256 / w.max(1)).clamp(1, 4);
    let big = crate::overlay::enlarged(&grid(&images, cols, w, h), cols * w, images.len() / cols * h, k);
    let sheet_path = a.out.join("sheet.png");
    write_png(&sheet_path, &big, (cols * w * k) as u32, ((images.len() / cols) * h * k) as u32)?;
    let clip_path = a.out.join("clip.gif");
    let panes = 1 + cams.len().min(CLIP_VIEWS);
    write_gif(&clip_path, &clip, (panes * w) as u32, h as u32, 100)?;
    let report = Report {
        command: "generate",
        generator: a.checkpoint.display().to_string(),
        autoencoder: a.autoencoder.display().to_string(),
        input: input.display().to_string(),
        task: cfg.task,
        dinov2: m.dino.is_some(),
        steps: a.steps,
        sampler: a.sampler,
        guidance: a.guidance,
        seed: a.seed,
        voxels: source,
        generate_seconds,
        frames,
        views: a.views as usize,
        sheet: name(&sheet_path),
        clip: name(&clip_path),
    };
    write_bytes(&a.out.join("generate.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    println!(
        "generated in {generate_seconds:.1} s; wrote {} frames of Gaussians, renders from {} views and {} to {} in {:.1} s",
        report.frames.len(),
        cams.len(),
        report.sheet,
        a.out.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The condition frame nearest frame `f` of the clip, un-normalised and resized to `w x h` for
/// the contact sheet (the image task's one frame for every column).
fn condition_frame(
    pixels: &[f32],
    task: GenerationTask,
    size: usize,
    f: usize,
    w: usize,
    h: usize,
) -> Vec<f32> {
    let n = task.frames();
    let i = if n == 1 { 0 } else { f * (n - 1) / (velox_models::velox::autoencoder::FRAMES - 1) };
    let plane = size * size;
    let frame = &pixels[i * 3 * plane..(i + 1) * 3 * plane];
    let mean = velox_models::velox::dinov2::IMAGENET_MEAN;
    let std = velox_models::velox::dinov2::IMAGENET_STD;
    let mut out = vec![0.0; w * h * 3];
    for y in 0..h {
        for x in 0..w {
            let (sy, sx) = (y * size / h, x * size / w);
            for c in 0..3 {
                out[3 * (y * w + x) + c] =
                    (frame[c * plane + sy * size + sx] * std[c] + mean[c]).clamp(0.0, 1.0);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sheet_picks_frames_evenly_and_grids_rows() {
        assert_eq!(sheet_frames(&(0..24).collect::<Vec<_>>()), vec![0, 4, 9, 13, 18, 23]);
        assert_eq!(sheet_frames(&[3]), vec![3]);
        assert_eq!(sheet_frames(&[1, 2]), vec![1, 2]);
        let a = vec![0.1; 2 * 2 * 3];
        let b = vec![0.2; 2 * 2 * 3];
        let g = grid(&[a.clone(), b.clone(), b.clone(), a.clone()], 2, 2, 2);
        assert_eq!(g.len(), 4 * 4 * 3);
        assert_eq!(g[0], 0.1);
        assert_eq!(g[3 * 2], 0.2);
        assert_eq!(g[3 * 8], 0.2);
    }
}
