//! Per-frame Gaussians (a `decode gaussians` or `generate` output, or another tool's numbered
//! PLY sequence) written in the files other viewers play, as `velox export` and Python's
//! `velox.export` write them:
//! - [`Format::PlySeq`]: `frame_FFFF.ply`, the frames' own 3D Gaussian splatting PLYs (their
//!   bytes, higher spherical harmonics kept), named as SuperSplat loads a sequence;
//! - [`Format::Splatv`]: one `clip.splatv`, a flipbook for splaTV's viewer and gsplat.js
//!   (`velox_io::splatv`), first seen from the scene's first supervision camera (the format
//!   holds the colour alone);
//! - [`Format::Spz`]: `frame_FFFF.spz`, Niantic's compressed format (`velox_io::spz`);
//! - [`Format::Glb`]: `frame_FFFF.glb`, glTF with `KHR_gaussian_splatting` (`velox_io::glb`).
//!
//! Higher spherical harmonics in the frames (degrees 1 to 3) go into the PLY sequence, SPZ and
//! glTF with them.
//!
//! Every frame is read and checked before anything is written.

use std::path::{Path, PathBuf};

use velox_engine::ops::raster::{Camera, GaussianData};
use velox_engine::{Error, FileOp, Result};
use velox_io::decoded::DecodeReport;
use velox_io::frames::{self, sequence_file};
use velox_io::ply::Sh;
use velox_io::splatv::SplatvCamera;
use velox_io::{glb, ply, read_parsed, splatv, spz, write_bytes};

/// The formats written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    PlySeq,
    Splatv,
    Spz,
    Glb,
}

impl Format {
    pub const ALL: [Format; 4] = [Format::PlySeq, Format::Splatv, Format::Spz, Format::Glb];

    /// The format's name (`ply-seq`, `splatv`, `spz`, `glb`).
    pub fn name(self) -> &'static str {
        match self {
            Format::PlySeq => "ply-seq",
            Format::Splatv => "splatv",
            Format::Spz => "spz",
            Format::Glb => "glb",
        }
    }

    /// The format named `name`.
    pub fn named(name: &str) -> Result<Format> {
        Format::ALL.into_iter().find(|f| f.name() == name).ok_or_else(|| {
            Error::setting("to", format!("{{to}} `{name}` is not a format: ply-seq, splatv, spz or glb"))
        })
    }
}

/// How to export.
#[derive(Clone, Debug)]
pub struct ExportOptions {
    pub format: Format,
    /// A folder (ply-seq, spz, glb) or the .splatv file; default `DIR/export/FORMAT` or
    /// `DIR/export/clip.splatv`.
    pub out: Option<PathBuf>,
    /// SPZ's version: 3, or 2 for readers from before version 3.
    pub spz_version: u32,
    /// The scene whose first supervision camera a .splatv opens with (default: the scene
    /// DIR's decode.json names; else 4 units out on +z, 20 degrees up, looking at the origin).
    pub scene: Option<PathBuf>,
}

/// What an export wrote.
#[derive(Clone, Debug)]
pub struct Exported {
    /// The files, in frame order.
    pub files: Vec<PathBuf>,
    pub frames: usize,
    pub gaussians: usize,
    /// The .splatv's camera's name.
    pub camera: Option<String>,
}

/// The frames of `dir`, frame number and file, in order.
fn frame_list(dir: &Path) -> Result<Vec<(usize, PathBuf)>> {
    if !dir.is_dir() {
        return Err(Error::Invalid(format!("{} is not a folder of per-frame Gaussians", dir.display())));
    }
    let list = match frames::frame_files(dir, "gaussians")? {
        list if !list.is_empty() => list,
        _ => frames::numbered_files(dir)?,
    };
    if list.is_empty() {
        return Err(Error::Invalid(format!(
            "{} holds no frames: expected gaussians_fFF.ply (velox decode gaussians, velox generate) or a \
             numbered PLY sequence (frame_0000.ply, frame_0001.ply, ...)",
            dir.display()
        )));
    }
    Ok(list)
}

/// The camera a .splatv opens with.
fn splatv_camera(dir: &Path, scene: Option<&Path>) -> Result<SplatvCamera> {
    let scene = scene.map(Path::to_path_buf).or_else(|| DecodeReport::read(dir).ok()?.scene());
    Ok(match scene {
        Some(scene) => {
            let cameras =
                velox_data::format::read_cameras(&scene).map_err(|e| Error::Invalid(e.to_string()))?;
            let camera = cameras.supervision.first().ok_or_else(|| {
                Error::Invalid(format!("{} has no supervision camera", scene.join("cameras.json").display()))
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

/// Exports the frames of `dir` (see the module docs).
pub fn export(dir: &Path, o: &ExportOptions) -> Result<Exported> {
    if !(2..=3).contains(&o.spz_version) {
        return Err(Error::setting(
            "spz_version",
            format!("{{spz_version}} {} is not 2 or 3", o.spz_version),
        ));
    }
    let list = frame_list(dir)?;
    let mut clip: Vec<(usize, GaussianData, Option<Sh>, Vec<u8>)> = Vec::with_capacity(list.len());
    for (f, path) in &list {
        // Read once: a PLY sequence writes these bytes.
        let (g, sh, bytes) = read_parsed(path, |bytes| {
            let (g, sh) = ply::from_bytes_sh(bytes)?;
            Ok((g, sh, bytes.to_vec()))
        })?;
        clip.push((*f, g, sh, bytes));
    }
    let out = o.out.clone().unwrap_or_else(|| {
        let export = dir.join("export");
        match o.format {
            Format::Splatv => export.join("clip.splatv"),
            other => export.join(other.name()),
        }
    });
    let folder =
        if o.format == Format::Splatv { out.parent().map(Path::to_path_buf) } else { Some(out.clone()) };
    if let Some(folder) = folder.filter(|f| !f.as_os_str().is_empty()) {
        std::fs::create_dir_all(&folder).map_err(|e| Error::file(&folder, FileOp::Write, e))?;
    }
    let gaussians = clip.iter().map(|(_, g, ..)| g.len()).sum();
    let frames = clip.len();
    if o.format == Format::Splatv {
        let camera = splatv_camera(dir, o.scene.as_deref())?;
        let clip: Vec<GaussianData> = clip.into_iter().map(|(_, g, ..)| g).collect();
        splatv::write(&out, &clip, &camera)?;
        return Ok(Exported { files: vec![out], frames, gaussians, camera: Some(camera.img_name) });
    }
    let ext = match o.format {
        Format::PlySeq => "ply",
        Format::Spz => "spz",
        _ => "glb",
    };
    let mut files = Vec::with_capacity(frames);
    for (f, g, sh, bytes) in &clip {
        let path = out.join(sequence_file(*f, ext));
        let written = match o.format {
            // The frame's own bytes.
            Format::PlySeq => write_bytes(&path, bytes),
            Format::Spz => {
                spz::to_bytes_sh(g, sh.as_ref(), o.spz_version).and_then(|b| write_bytes(&path, &b))
            }
            _ => glb::to_bytes_sh(g, sh.as_ref()).and_then(|b| write_bytes(&path, &b)),
        };
        written.map_err(|e| Error::Invalid(format!("frame {f}: {e}")))?;
        files.push(path);
    }
    Ok(Exported { files, frames, gaussians, camera: None })
}
