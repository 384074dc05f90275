//! `velox decode points|gaussians`: encodes a 4D colour point cloud with a trained autoencoder
//! and decodes the tokens, one file per requested frame, through `velox_models::velox::decode`
//! (its docs give the seed rule and the voxel sources).
//!
//! - `decode points` samples the 4D surface decoder (Heun or Euler, N steps) at each frame time
//!   and writes `points_fFF.ply`: binary little-endian PLY, one `vertex` element with the float
//!   properties `x y z tau` (tau = frame / 100, the same for every point of a file).
//! - `decode gaussians` decodes the Gaussians of each frame and writes `gaussians_fFF.ply` in
//!   the 3D Gaussian splatting layout (`velox_io::ply`; `velox render` reads it).
//!   The Gaussian decoder's queries are the occupied voxels of the frame: by default those of
//!   surface points sampled from the tokens (`--voxels surface`), or those of the input cloud's
//!   points of that frame (`--voxels cloud`, as in training).
//!
//! Both write `decode.json` beside the files: the checkpoint, the frames, each file and its
//! count. The input is a scene folder (its `points.ply`) or a PLY of float `x y z r g b tau`
//! (`velox_data::format::write_ply`'s layout), checked by `velox_data::format::read_ply`, or a
//! video folder; a capture imported in windows is decoded window by window ([`clips`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;
use velox_engine::ops::raster::{render, Camera};

use crate::overlay::clip_gif;
use velox_engine::{Gpu, Precision};
use velox_io::cloud::CHANNELS;
use velox_io::decoded::{DecodeReport, DecodedFrame};
use velox_io::{frames, mesh, ply};
use velox_models::velox::autoencoder::{Autoencoder, FRAMES};
use velox_models::velox::decode::{
    frame_points, sampler_name, Decoding, FrameOutput, Sampling, VoxelSource, WrittenFrame,
};
use velox_models::velox::surface::Sampler;
use velox_models::velox::voxels::VoxelDecoder;
use velox_models::Model;

use crate::CliResult;

#[derive(clap::Subcommand)]
pub enum DecodeCommand {
    /// Surface points of each requested frame, sampled by the 4D surface decoder, as PLY.
    Points(PointsArgs),
    /// 3D Gaussians of each requested frame, as 3D Gaussian splatting PLY.
    Gaussians(GaussiansArgs),
    /// A triangle mesh of each requested frame's surface, from points sampled by the surface
    /// decoder (see `velox_data::surface`), as PLY, OBJ and glTF binary.
    Mesh(MeshArgs),
}

#[derive(clap::Args)]
pub struct MeshArgs {
    #[command(flatten)]
    common: CommonArgs,
    /// The surface points the mesh is made from.
    #[command(flatten)]
    sampling: SamplingArgs,
    /// Grid cells along the surface's longest side: the mesh's detail (8 to 256).
    #[arg(long, default_value_t = 96)]
    resolution: usize,
    /// The files written for each frame: any of ply, obj and glb, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "ply,obj,glb")]
    format: Vec<MeshFormatArg>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MeshFormatArg {
    Ply,
    Obj,
    Glb,
}

impl From<MeshFormatArg> for mesh::Format {
    fn from(f: MeshFormatArg) -> mesh::Format {
        match f {
            MeshFormatArg::Ply => mesh::Format::Ply,
            MeshFormatArg::Obj => mesh::Format::Obj,
            MeshFormatArg::Glb => mesh::Format::Glb,
        }
    }
}

#[derive(clap::Args)]
pub struct CommonArgs {
    /// Autoencoder checkpoint (safetensors, as `Autoencoder::save` writes it).
    #[arg(long)]
    checkpoint: PathBuf,
    /// The input 4D cloud: a scene folder (its points.ply), a PLY of float x y z r g b tau, or
    /// a video folder from `velox import rgbd` or `velox import video` (its RGBD frames
    /// back-projected: at most 100000 of their pixels). A capture imported in windows is
    /// decoded window by window, its frames named by the capture's.
    #[arg(long)]
    cloud: PathBuf,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
    /// Frames to decode: comma-separated indices in 0..=23 (of a capture imported in windows,
    /// the capture's frames they cover), or `all`.
    #[arg(long, default_value = "all", value_parser = parse_frames)]
    frames: Frames,
    /// Seed of the encoder's queries and of the sampler's noise.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Precision of the networks: f32, or f16 (matrix products and attention on f16 operands
    /// with f32 accumulation).
    #[arg(long, value_enum, default_value_t = PrecisionArg::F32)]
    precision: PrecisionArg,
}

/// `--precision` of the commands that run a trained model.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum PrecisionArg {
    F32,
    F16,
}

impl From<PrecisionArg> for Precision {
    fn from(p: PrecisionArg) -> Precision {
        match p {
            PrecisionArg::F32 => Precision::F32,
            PrecisionArg::F16 => Precision::F16,
        }
    }
}

#[derive(clap::Args)]
pub struct SamplingArgs {
    /// Surface points sampled per frame.
    #[arg(long, default_value_t = 16384, value_parser = clap::value_parser!(u64).range(1..=100_000_000))]
    points: u64,
    /// Integration steps of the sampler.
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u64).range(1..=10_000))]
    steps: u64,
    #[arg(long, value_enum, default_value_t = SamplerArg::Heun)]
    sampler: SamplerArg,
}

impl SamplingArgs {
    fn sampling(&self) -> Sampling {
        Sampling { points: self.points as usize, steps: self.steps as usize, sampler: self.sampler.into() }
    }
}

#[derive(clap::Args)]
pub struct PointsArgs {
    #[command(flatten)]
    common: CommonArgs,
    #[command(flatten)]
    sampling: SamplingArgs,
}

#[derive(clap::Args)]
pub struct GaussiansArgs {
    #[command(flatten)]
    common: CommonArgs,
    /// Where the Gaussian decoder's occupied voxels come from [default: predicted with
    /// --voxel-decoder, else surface].
    #[arg(long, value_enum)]
    voxels: Option<VoxelArg>,
    /// A voxel decoder (`velox train voxels`) trained on this autoencoder's tokens, for
    /// `--voxels predicted`.
    #[arg(long)]
    voxel_decoder: Option<PathBuf>,
    /// Sampling of the surface points whose voxels are the queries (`--voxels surface`).
    #[command(flatten)]
    sampling: SamplingArgs,
    /// Also write the decoded frames as an animated GIF (`clip.gif`, and each frame as
    /// `clip/fFF.png`) beside the truth: the scene's first supervision view (needs --cloud to
    /// be a dataset scene).
    #[arg(long)]
    gif: bool,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SamplerArg {
    /// Heun's method: two velocities per step, second order.
    Heun,
    /// Euler's method: one velocity per step.
    Euler,
}

impl From<SamplerArg> for Sampler {
    fn from(s: SamplerArg) -> Sampler {
        match s {
            SamplerArg::Heun => Sampler::Heun,
            SamplerArg::Euler => Sampler::Euler,
        }
    }
}

/// `--voxels`: where the Gaussian decoder's occupied voxels come from.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum VoxelArg {
    /// Voxels a voxel decoder predicts from the tokens (needs `--voxel-decoder`).
    Predicted,
    /// Voxels of surface points sampled from the tokens (needs nothing but the tokens).
    Surface,
    /// Voxels of the input cloud's points of the frame (as in training).
    #[value(alias = "cloud")]
    Input,
}

impl From<VoxelArg> for VoxelSource {
    fn from(v: VoxelArg) -> VoxelSource {
        match v {
            VoxelArg::Predicted => VoxelSource::Predicted,
            VoxelArg::Surface => VoxelSource::Surface,
            VoxelArg::Input => VoxelSource::Input,
        }
    }
}

/// The voxel decoder of `--voxel-decoder`, checked against the autoencoder `checkpoint`, if
/// one is given; an error if `sources` want predicted voxels without one.
pub fn voxel_decoder(
    gpu: &Gpu,
    path: Option<&Path>,
    checkpoint: &Path,
    sources: &[VoxelSource],
) -> CliResult<Option<VoxelDecoder>> {
    let Some(path) = path else {
        if sources.contains(&VoxelSource::Predicted) {
            return Err("--voxels predicted needs a voxel decoder: --voxel-decoder CHECKPOINT".into());
        }
        return Ok(None);
    };
    let d = VoxelDecoder::load(gpu, path)?;
    d.check_encoder(checkpoint)?;
    Ok(Some(d))
}

/// Requested frames: `None` for all of them. Checked against the input's frames once it is
/// read (a clip has 24; a capture imported in windows, every frame its windows cover).
#[derive(Clone, Debug)]
pub struct Frames(pub Option<Vec<usize>>);

pub fn parse_frames(s: &str) -> Result<Frames, String> {
    if s.trim() == "all" {
        return Ok(Frames(None));
    }
    let mut frames = Vec::new();
    for part in s.split(',') {
        let f: usize = part.trim().parse().map_err(|_| {
            format!("`{}` is not a frame index (use numbers like 0,5,10 or `all`)", part.trim())
        })?;
        if !frames.contains(&f) {
            frames.push(f);
        }
    }
    Ok(Frames(Some(frames)))
}

impl Frames {
    /// The frames asked for among `available` (in their order for `all`), or an error naming
    /// the first that is not one of them.
    pub fn among(&self, available: &[usize]) -> CliResult<Vec<usize>> {
        let Some(list) = &self.0 else { return Ok(available.to_vec()) };
        if let Some(f) = list.iter().find(|f| !available.contains(f)) {
            let (first, last) = (available.first().unwrap_or(&0), available.last().unwrap_or(&0));
            return Err(format!("frame {f} is out of range: the clip has frames {first} to {last}").into());
        }
        Ok(list.clone())
    }
}

/// One clip to decode: its cloud (host rows), and each frame to write with its name. A
/// capture imported in windows (`velox import rgbd --windows`) is a clip per window, each
/// writing the frames after those the windows before it cover (`window_shares`), named by the
/// capture's frames.
pub struct Clip {
    pub cloud: Vec<f32>,
    pub frames: Vec<(usize, usize)>,
}

/// The clips of `--cloud`, with the frames `frames` picks of them (windows none of whose
/// frames are asked for are left out); and the number of windows (0: not a windowed capture).
pub fn clips(cloud: &Path, frames: &Frames) -> CliResult<(Vec<Clip>, usize)> {
    let Some(windows) = velox_tasks::track::read_windows(cloud)? else {
        let wanted = frames.among(&(0..FRAMES).collect::<Vec<_>>())?;
        let frames = wanted.into_iter().map(|f| (f, f)).collect();
        return Ok((vec![Clip { cloud: read_cloud(cloud)?, frames }], 0));
    };
    let lists: Vec<&[usize]> = windows.iter().map(|w| &w.1[..]).collect();
    let shares = velox_tasks::track::window_shares(&lists)?;
    let own: Vec<&[usize]> = lists.iter().zip(&shares).map(|(f, &s)| &f[s..]).collect();
    let wanted = frames.among(&own.concat())?;
    let mut clips = Vec::new();
    for ((video, list), &shared) in windows.iter().zip(&shares) {
        let frames: Vec<(usize, usize)> =
            (shared..FRAMES).filter(|&j| wanted.contains(&list[j])).map(|j| (j, list[j])).collect();
        if frames.is_empty() {
            continue;
        }
        let rows = velox_data::rgbd::rgbd_cloud(video, velox_data::rgbd::DEFAULT_POINTS, 0)
            .map_err(|e| format!("reading the cloud of the window from frame {}: {e}", list[0]))?;
        clips.push(Clip { cloud: rows.iter().flatten().copied().collect(), frames });
    }
    Ok((clips, windows.len()))
}

/// The cloud of a scene folder (its points.ply), a PLY file or a video folder, as host rows
/// (`velox_data::format::read_cloud` validates them).
pub fn read_cloud(path: &Path) -> CliResult<Vec<f32>> {
    Ok(velox_data::format::read_cloud(path).map_err(|e| format!("reading the cloud: {e}"))?)
}

/// A progress bar over `len` items of `what`.
pub fn progress(len: usize, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len as u64);
    let template = format!("{{bar:40}} {{pos}}/{{len}} {what}, {{elapsed}} elapsed, {{eta}} left {{msg}}");
    bar.set_style(ProgressStyle::with_template(&template).unwrap_or_else(|_| ProgressStyle::default_bar()));
    bar
}

/// Frame `f` of the Gaussians a decoding wrote (`written`), read back from its file and
/// rendered from `camera` on `background` (the scene's): a clip's pane.
pub fn render_written(
    gpu: &Gpu,
    written: &[WrittenFrame],
    f: usize,
    camera: &Camera,
    background: [f32; 3],
) -> CliResult<Vec<Vec<f32>>> {
    let path =
        written.iter().find(|w| w.frame == f).map(|w| &w.path).ok_or("a frame that was not decoded")?;
    let g = ply::read(path)?.upload(gpu)?;
    Ok(vec![render(gpu, &g, camera, background)?.image.rgb.read()?])
}

/// What a decoding wrote, for `decode.json` beside its files: which checkpoint decoded which
/// cloud (a scene folder, whose cameras and truth `velox view` then shows beside the frames),
/// how, and each frame's file.
pub struct DecodeRecord<'a> {
    /// `decode points`, `decode gaussians` or `decode mesh`.
    pub command: &'static str,
    pub checkpoint: &'a Path,
    pub cloud: &'a Path,
    pub ae: &'a Autoencoder,
    pub input_points: usize,
    pub voxels: Option<VoxelSource>,
    pub sampling: &'a Sampling,
    pub encode_seconds: f64,
}

/// Writes `out/decode.json` listing `written` (frames of one kind) and returns its path.
pub fn write_report(out: &Path, record: &DecodeRecord, written: &[WrittenFrame]) -> CliResult<PathBuf> {
    let frames = written
        .iter()
        .map(|w| DecodedFrame {
            frame: w.frame,
            tau: w.tau,
            file: name(&w.path),
            count: w.count,
            voxels: w.voxels,
            seconds: w.seconds,
        })
        .collect();
    let report = DecodeReport {
        command: record.command.into(),
        checkpoint: record.checkpoint.display().to_string(),
        // Absolute, so that the viewer finds the scene from any folder.
        cloud: std::path::absolute(record.cloud)
            .unwrap_or_else(|_| record.cloud.to_path_buf())
            .display()
            .to_string(),
        config: record.ae.cfg.name.clone(),
        precision: record.ae.precision().name().into(),
        input_points: record.input_points,
        voxels: record.voxels.map(|v| v.name().into()),
        sampler: sampler_name(record.sampling.sampler).into(),
        steps: record.sampling.steps,
        points: record.sampling.points,
        encode_seconds: record.encode_seconds,
        frames,
    };
    Ok(report.write(out)?)
}

pub fn run(cmd: DecodeCommand) -> CliResult<()> {
    let (common, sampling, voxels) = match &cmd {
        DecodeCommand::Points(a) => (&a.common, &a.sampling, None),
        DecodeCommand::Mesh(a) => (&a.common, &a.sampling, None),
        DecodeCommand::Gaussians(a) => {
            let default = if a.voxel_decoder.is_some() { VoxelArg::Predicted } else { VoxelArg::Surface };
            (&a.common, &a.sampling, Some(VoxelSource::from(a.voxels.unwrap_or(default))))
        }
    };
    let decoder_path = match &cmd {
        DecodeCommand::Gaussians(a) => a.voxel_decoder.clone(),
        DecodeCommand::Points(_) | DecodeCommand::Mesh(_) => None,
    };
    let command = match &cmd {
        DecodeCommand::Points(_) => "decode points",
        DecodeCommand::Gaussians(_) => "decode gaussians",
        DecodeCommand::Mesh(a) => {
            if !velox_data::surface::RESOLUTIONS.contains(&a.resolution) {
                return Err(format!("--resolution {}: give 8 to 256 cells", a.resolution).into());
            }
            "decode mesh"
        }
    };
    let gif = matches!(&cmd, DecodeCommand::Gaussians(a) if a.gif);
    if gif && !common.cloud.join("cameras.json").is_file() {
        return Err(format!(
            "--gif shows the decoded frames beside the truth: --cloud must be a dataset scene folder, {} is not",
            common.cloud.display()
        )
        .into());
    }
    let (clips, windows) = clips(&common.cloud, &common.frames)?;
    if voxels == Some(VoxelSource::Input) {
        for clip in &clips {
            let per_frame = frame_points(&clip.cloud);
            if let Some(&(_, f)) = clip.frames.iter().find(|&&(j, _)| per_frame[j].is_empty()) {
                return Err(format!(
                    "frame {f} has no points in {}, so it has no voxels: choose other frames or --voxels surface",
                    common.cloud.display()
                )
                .into());
            }
        }
    }
    let input_points: usize = clips.iter().map(|c| c.cloud.len() / CHANNELS).sum();
    let frame_count: usize = clips.iter().map(|c| c.frames.len()).sum();
    let gpu = Gpu::new()?;
    let mut ae = Autoencoder::load(&gpu, &common.checkpoint)?;
    ae.set_precision(common.precision.into())?;
    std::fs::create_dir_all(&common.out).map_err(|e| format!("creating {}: {e}", common.out.display()))?;
    let what = match &cmd {
        DecodeCommand::Points(_) => "surface points",
        DecodeCommand::Gaussians(_) => "Gaussians",
        DecodeCommand::Mesh(_) => "surface meshes",
    };
    let windowed = match windows {
        0 => String::new(),
        n => format!(", a capture in {n} windows of {FRAMES} frames, {} of them encoded", clips.len()),
    };
    println!(
        "decoding {what} of {frame_count} frames of {} ({input_points} points{windowed}) with the {} autoencoder \
         in {} on {}",
        common.cloud.display(),
        ae.cfg.name,
        ae.precision().name(),
        gpu.caps().name
    );
    let start = Instant::now();
    let sources: Vec<VoxelSource> = voxels.into_iter().collect();
    let decoder = voxel_decoder(&gpu, decoder_path.as_deref(), &common.checkpoint, &sources)?;
    let bar = progress(frame_count, "frames");
    let output = match voxels {
        None => FrameOutput::Points,
        Some(source) => FrameOutput::Gaussians(source),
    };
    // Called before each frame: the bar counts the frames done.
    let mut done = 0;
    let mut on_frame = |f: usize| {
        bar.set_position(done);
        bar.set_message(format!("frame {f}"));
        done += 1;
    };
    let mut written = Vec::with_capacity(frame_count);
    let mut encode_seconds = 0.0;
    for clip in &clips {
        let encoding = Instant::now();
        let mut decoding = Decoding::encode(&ae, &clip.cloud, common.seed)?;
        if let Some(d) = &decoder {
            decoding = decoding.with_voxel_decoder(d)?;
        }
        encode_seconds += encoding.elapsed().as_secs_f64();
        written.extend(match &cmd {
            DecodeCommand::Mesh(a) => write_meshes(&decoding, a, &clip.frames, &mut on_frame)?,
            _ => decoding.write_frames_named(
                &clip.frames,
                output,
                &sampling.sampling(),
                &common.out,
                &mut on_frame,
            )?,
        });
    }
    bar.finish_and_clear();
    let record = DecodeRecord {
        command,
        checkpoint: &common.checkpoint,
        cloud: &common.cloud,
        ae: &ae,
        input_points,
        voxels,
        sampling: &sampling.sampling(),
        encode_seconds,
    };
    write_report(&common.out, &record, &written)?;
    if gif {
        // The frames as written, read back from their files.
        let (gif, pngs) = (common.out.join("clip.gif"), common.out.join("clip"));
        let render_frame = |f: usize, camera: &Camera, bg| render_written(&gpu, &written, f, camera, bg);
        let frames: Vec<usize> = written.iter().map(|w| w.frame).collect();
        clip_gif(&common.cloud, &frames, render_frame, &gif, 80, Some(&pngs))?;
        println!("wrote {} and its frames under {} (ground truth | decoded)", gif.display(), pngs.display());
    }
    let files = match &cmd {
        DecodeCommand::Mesh(a) => written.len() * a.format.len(),
        _ => written.len(),
    };
    println!(
        "wrote {files} files to {} in {:.1} s (decode.json lists them)",
        common.out.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Samples each requested frame's surface, meshes it and writes `mesh_fFF.EXT` in every
/// format asked for; the frames listed name the first format's file and count triangles.
fn write_meshes(
    decoding: &Decoding,
    a: &MeshArgs,
    frames: &[(usize, usize)],
    on_frame: &mut dyn FnMut(usize),
) -> CliResult<Vec<WrittenFrame>> {
    let mut written = Vec::new();
    for &(frame, name) in frames {
        on_frame(name);
        let start = Instant::now();
        let xyz = decoding.surface_points(frame, &a.sampling.sampling())?;
        let m = velox_data::surface::mesh_of_points(&xyz, a.resolution)?;
        let mut first = None;
        for &format in &a.format {
            let format = mesh::Format::from(format);
            let path = a.common.out.join(frames::frame_file_as("mesh", name, format.extension()));
            mesh::write(&path, &m, format)?;
            first.get_or_insert(path);
        }
        let path = first.ok_or("--format names no format")?;
        written.push(WrittenFrame {
            frame: name,
            tau: frames::tau_of(frame),
            path,
            count: m.triangles.len(),
            voxels: None,
            seconds: start.elapsed().as_secs_f64(),
        });
    }
    Ok(written)
}

pub fn name(p: &Path) -> String {
    p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_parse_with_clear_errors() {
        let clip: Vec<usize> = (0..FRAMES).collect();
        assert_eq!(parse_frames("all").unwrap().among(&clip).unwrap(), clip);
        assert_eq!(parse_frames("0, 5,10,5").unwrap().among(&clip).unwrap(), vec![0, 5, 10]);
        let e = parse_frames("99").unwrap().among(&clip).unwrap_err().to_string();
        assert!(e.contains("frame 99 is out of range: the clip has frames 0 to 23"), "{e}");
        assert!(parse_frames("x").unwrap_err().contains("not a frame index"));
    }
}
