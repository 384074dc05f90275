//! `velox export DIR --to ply-seq|splatv|spz|glb`: per-frame Gaussians in the files other
//! viewers play, by `velox_tasks::export` (its docs list what each format writes).

use std::path::PathBuf;

use velox_tasks::export::{export, ExportOptions, Format};

use crate::CliResult;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum FormatArg {
    /// A numbered 3D Gaussian splatting PLY sequence (SuperSplat, PlayCanvas).
    PlySeq,
    /// One .splatv flipbook (splaTV, gsplat.js).
    Splatv,
    /// One SPZ file a frame (Niantic's format; SuperSplat, Spark).
    Spz,
    /// One glTF binary a frame with KHR_gaussian_splatting.
    Glb,
}

impl From<FormatArg> for Format {
    fn from(f: FormatArg) -> Format {
        match f {
            FormatArg::PlySeq => Format::PlySeq,
            FormatArg::Splatv => Format::Splatv,
            FormatArg::Spz => Format::Spz,
            FormatArg::Glb => Format::Glb,
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
    to: FormatArg,
    /// Where to write: a folder (ply-seq, spz, glb) or the .splatv file (default:
    /// DIR/export/FORMAT, DIR/export/clip.splatv).
    #[arg(long)]
    out: Option<PathBuf>,
    /// The SPZ version written: 3 (rotations in 4 bytes) or 2 (3 bytes, for readers from before
    /// version 3; rotations near a half turn lose up to a fifth of a radian).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(2..=3))]
    spz_version: u32,
    /// The scene whose first supervision camera a .splatv opens with (default: the scene the
    /// folder's decode.json names; else a camera 4 units out on +z, 20 degrees up, looking at
    /// the origin).
    #[arg(long)]
    scene: Option<PathBuf>,
}

pub fn run(a: &ExportArgs) -> CliResult<()> {
    let format = Format::from(a.to);
    let options =
        ExportOptions { format, out: a.out.clone(), spz_version: a.spz_version, scene: a.scene.clone() };
    let done = export(&a.dir, &options)?;
    let name = |p: &PathBuf| p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    match &done.camera {
        Some(camera) => println!(
            "wrote {} ({} frames, {} Gaussians, opening on the {camera} camera)",
            done.files[0].display(),
            done.frames,
            done.gaussians
        ),
        None => println!(
            "wrote {} frames ({} Gaussians) as {} to {}: {} ... {}",
            done.frames,
            done.gaussians,
            format.name(),
            done.files[0].parent().unwrap_or(&a.dir).display(),
            name(&done.files[0]),
            name(&done.files[done.files.len() - 1])
        ),
    }
    Ok(())
}
