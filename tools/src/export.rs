//! `velox export DIR --to ply-seq|splatv|spz|glb`: per-frame Gaussians (a `decode gaussians`
//! or `generate` output, or another tool's numbered PLY sequence) in the files other viewers
//! play:
//! - `ply-seq`: `frame_FFFF.ply`, 3D Gaussian splatting PLYs named as SuperSplat loads a
//!   sequence (select them all; each frame its number);
//! - `splatv`: one `clip.splatv`, a flipbook for splaTV's viewer and gsplat.js
//!   (`velox_io::splatv`), first seen from the scene's first supervision camera;
//! - `spz`: `frame_FFFF.spz`, Niantic's compressed format (`velox_io::spz`);
//! - `glb`: `frame_FFFF.glb`, glTF with `KHR_gaussian_splatting` (`velox_io::glb`).
//!
//! Every frame is read and checked before anything is written.

use std::path::{Path, PathBuf};

use velox_engine::ops::raster::{Camera, GaussianData};
use velox_io::decoded::DecodeReport;
use velox_io::frames::{self, sequence_file};
use velox_io::splatv::SplatvCamera;
use velox_io::{glb, ply, splatv, spz, write_bytes};

use crate::CliResult;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// A numbered 3D Gaussian splatting PLY sequence (SuperSplat, PlayCanvas).
    PlySeq,
    /// One .splatv flipbook (splaTV, gsplat.js).
    Splatv,
    /// One SPZ file a frame (Niantic's format; SuperSplat, Spark).
    Spz,
    /// One glTF binary a frame with KHR_gaussian_splatting.
    Glb,
}

impl Format {
    fn name(self) -> &'static str {
        match self {
            Format::PlySeq => "ply-seq",
            Format::Splatv => "splatv",
            Format::Spz => "spz",
            Format::Glb => "glb",
        }
    }
}

#[derive(clap::Args)]
pub struct ExportArgs {
    /// A folder of per-frame Gaussians: gaussians_fFF.ply (velox decode gaussians, velox
    /// generate) or another tool's numbered PLY sequence.
    dir: PathBuf,
    /// The format to write.
    #[arg(long, value_enum)]
    to: Format,
    /// Where to write: a folder (ply-seq, spz, glb) or the .splatv file (default:
    /// DIR/export/FORMAT, DIR/export/clip.splatv).
    #[arg(long)]
    out: Option<PathBuf>,
    /// The SPZ version written: 3 (rotations in 4 bytes) or 2 (3 bytes, for readers from before
    /// version 3; rotations near a half turn lose up to a tenth of a radian).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(2..=3))]
    spz_version: u32,
    /// The scene whose first supervision camera a .splatv opens with (default: the scene the
    /// folder's decode.json names; else a camera 4 units out on +z, 20 degrees up, looking at
    /// the origin).
    #[arg(long)]
    scene: Option<PathBuf>,
}

/// The frames of `dir`, frame number and file, in order.
fn frame_list(dir: &Path) -> CliResult<Vec<(usize, PathBuf)>> {
    if !dir.is_dir() {
        return Err(format!("{} is not a folder of per-frame Gaussians", dir.display()).into());
    }
    let list = match frames::frame_files(dir, "gaussians")? {
        list if !list.is_empty() => list,
        _ => frames::numbered_files(dir)?,
    };
    if list.is_empty() {
        return Err(format!(
            "{} holds no frames: expected gaussians_fFF.ply (velox decode gaussians, velox generate) or a \
             numbered PLY sequence (frame_0000.ply, frame_0001.ply, ...)",
            dir.display()
        )
        .into());
    }
    Ok(list)
}

/// The camera a .splatv opens with.
fn splatv_camera(a: &ExportArgs) -> CliResult<SplatvCamera> {
    let scene = a.scene.clone().or_else(|| DecodeReport::read(&a.dir).ok()?.scene());
    Ok(match scene {
        Some(scene) => {
            let cameras = velox_data::format::read_cameras(&scene)?;
            let camera = cameras.supervision.first().ok_or_else(|| {
                format!("{} has no supervision camera", scene.join("cameras.json").display())
            })?;
            SplatvCamera::of(camera, "supervision 0")
        }
        None => {
            let el = 20f32.to_radians();
            let eye = [0.0, 4.0 * el.sin(), 4.0 * el.cos()];
            SplatvCamera::of(&Camera::look_at(eye, [0.0; 3], [0.0, 1.0, 0.0], 50.0, 512, 512), "default")
        }
    })
}

pub fn run(a: &ExportArgs) -> CliResult<()> {
    let list = frame_list(&a.dir)?;
    // Every frame read and checked first; a PLY sequence copies the files' bytes (keeping any
    // higher spherical harmonics another tool wrote).
    let mut clip: Vec<(usize, GaussianData, &Path)> = Vec::with_capacity(list.len());
    for (f, path) in &list {
        clip.push((*f, ply::read(path)?, path));
    }
    let out = a.out.clone().unwrap_or_else(|| {
        let export = a.dir.join("export");
        match a.to {
            Format::Splatv => export.join("clip.splatv"),
            other => export.join(other.name()),
        }
    });
    let folder = if a.to == Format::Splatv { out.parent().map(Path::to_path_buf) } else { Some(out.clone()) };
    if let Some(folder) = folder.filter(|f| !f.as_os_str().is_empty()) {
        std::fs::create_dir_all(&folder).map_err(|e| format!("creating {}: {e}", folder.display()))?;
    }
    let gaussians: usize = clip.iter().map(|(_, g, _)| g.len()).sum();
    match a.to {
        Format::Splatv => {
            let camera = splatv_camera(a)?;
            let frames: Vec<GaussianData> = clip.into_iter().map(|(_, g, _)| g).collect();
            splatv::write(&out, &frames, &camera)?;
            println!(
                "wrote {} ({} frames, {gaussians} Gaussians, opening on the {} camera)",
                out.display(),
                frames.len(),
                camera.img_name
            );
        }
        format => {
            let ext = match format {
                Format::PlySeq => "ply",
                Format::Spz => "spz",
                _ => "glb",
            };
            for (f, g, source) in &clip {
                let path = out.join(sequence_file(*f, ext));
                let written = match format {
                    Format::PlySeq => std::fs::read(source)
                        .map_err(|e| velox_engine::Error::file(source, velox_engine::FileOp::Read, e))
                        .and_then(|bytes| write_bytes(&path, &bytes)),
                    Format::Spz => spz::write(&path, g, a.spz_version),
                    _ => glb::write(&path, g),
                };
                written.map_err(|e| format!("frame {f}: {e}"))?;
            }
            println!(
                "wrote {} frames ({gaussians} Gaussians) as {} to {}: {} ... {}",
                clip.len(),
                format.name(),
                out.display(),
                sequence_file(clip[0].0, ext),
                sequence_file(clip[clip.len() - 1].0, ext)
            );
        }
    }
    Ok(())
}
