//! velox-io: the files Velox reads and writes, below the models and the data that use them.
//!
//! File formats users see: Gaussians as PLY in the 3D Gaussian splatting layout ([`ply`]), and
//! for other viewers as SPZ ([`spz`]), `.splatv` flipbooks ([`splatv`]) and glTF with
//! `KHR_gaussian_splatting` ([`glb`]); surface meshes as PLY, OBJ and glTF ([`mesh`]);
//! images as PNG and depth as EXR ([`image`]), and the colour point cloud every model and
//! dataset passes around ([`cloud`]: its layout and validation), and numpy's archives
//! ([`npz`], TAPVid-3D's files). Every reader names what is
//! wrong with a bad file.
//!
//! Every file the program writes goes through [`write_atomically`] (or [`write_bytes`]): the
//! content is written in full to `.<file name>.tmp` in the same folder, flushed and synced to
//! disk, renamed over the target, and the folder is synced, so a crash, a full disk or a file
//! size limit leaves either the old file or the new one, never half of one, and the error names
//! the file and what went wrong.

pub mod cloud;
pub mod decoded;
pub mod frames;
pub mod glb;
pub mod image;
pub mod mesh;
pub mod npz;
pub mod ply;
pub mod splatv;
pub mod spz;
pub mod tracks;

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

#[cfg(test)]
use velox_engine::ops::raster::GaussianData;
use velox_engine::{Error, FileOp, Result};

/// The temporary file a write of `path` goes through before it is renamed over `path`.
pub fn temp_path(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp"))
}

/// Writes `path` through a temporary file in the same folder (the same file system, so the
/// rename is atomic): `write` fills the temporary file; then it is flushed, synced, renamed over
/// `path`, and the folder is synced so the rename itself is durable. When anything fails
/// (`write` included) the temporary file is removed, `path` is left as it was, and the error
/// names `path` and the cause.
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> Result<()> {
    let failed = |e: std::io::Error| Error::file(path, FileOp::Write, e);
    if path.file_name().is_none() {
        return Err(failed(std::io::Error::new(std::io::ErrorKind::InvalidInput, "the path names no file")));
    }
    let tmp = temp_path(path);
    let written = (|| {
        let mut w = BufWriter::new(File::create(&tmp)?);
        write(&mut w)?;
        let f = w.into_inner().map_err(|e| e.into_error())?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = written {
        // Only a file of ours is removed; a folder in its place is left as it is.
        if tmp.is_file() {
            let _ = std::fs::remove_file(&tmp);
        }
        return Err(failed(e));
    }
    sync_dir(path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."))).map_err(failed)
}

/// Writes `bytes` to `path` atomically (see [`write_atomically`]).
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomically(path, |w| w.write_all(bytes))
}

#[cfg(unix)]
fn sync_dir(dir: &Path) -> std::io::Result<()> {
    File::open(dir)?.sync_all()
}

#[cfg(not(unix))]
fn sync_dir(_dir: &Path) -> std::io::Result<()> {
    // Windows cannot open a folder as a file; its rename is durable once the file is flushed.
    Ok(())
}

/// A file whose bytes its reader refused (see [`read_error`] for one that could not be read).
pub(crate) fn content_error(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::file(path, FileOp::Content, e)
}

/// The file at `path` parsed by `parse`, whose complaints about the bytes become errors naming
/// the file (as [`content_error`]); a file that cannot be read is a [`read_error`].
pub fn read_parsed<T>(path: &Path, parse: impl FnOnce(&[u8]) -> Result<T>) -> Result<T> {
    let bytes = std::fs::read(path).map_err(|e| read_error(path, e))?;
    parse(&bytes).map_err(|e| match e {
        Error::Invalid(why) => content_error(path, why),
        other => other,
    })
}

/// Writes `value` as pretty JSON to `path` (atomically) and returns the path.
pub(crate) fn write_json<T: serde::Serialize>(path: PathBuf, value: &T) -> Result<PathBuf> {
    let json = serde_json::to_string_pretty(value).map_err(|e| content_error(&path, e))?;
    write_bytes(&path, json.as_bytes())?;
    Ok(path)
}

/// `path` when it is a dataset scene folder (it holds `cameras.json`): the scene a decode or
/// track output names.
pub fn scene_folder(path: &str) -> Option<PathBuf> {
    let folder = PathBuf::from(path);
    folder.join("cameras.json").is_file().then_some(folder)
}

/// JSON bytes as a `T`.
pub(crate) fn parse_json<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T> {
    serde_json::from_slice(bytes).map_err(|e| Error::Invalid(e.to_string()))
}

/// Reads the JSON file at `path` as a `T`; a file that is not one is an error naming it.
pub(crate) fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    read_parsed(path, parse_json)
}

/// A file that could not be opened or read.
pub(crate) fn read_error(path: &Path, e: std::io::Error) -> Error {
    Error::file(path, FileOp::Read, e)
}

/// Random Gaussians for the format tests: means uniform in +-`spread`, log-scales in
/// `log_scales`, random quaternions (unnormalised), opacity logits in +-4, colours in [0, 1).
#[cfg(test)]
pub(crate) fn test_gaussians(n: usize, seed: u64, spread: f64, log_scales: (f64, f64)) -> GaussianData {
    let mut rng = velox_engine::rng::Rng::new(seed);
    let mut g = GaussianData::default();
    for _ in 0..n {
        let mean = [0; 3].map(|_| rng.range(-spread, spread) as f32);
        let ls = [0; 3].map(|_| rng.range(log_scales.0, log_scales.1) as f32);
        let q = [0; 4].map(|_| rng.normal() as f32);
        let c = [0; 3].map(|_| rng.uniform() as f32);
        g.push(mean, ls, q, rng.range(-4.0, 4.0) as f32, c);
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("velox-files-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn a_failed_write_leaves_no_temporary_and_no_target() {
        let dir = temp_dir("fails");
        let path = dir.join("out.bin");
        let e = write_atomically(&path, |w| {
            w.write_all(&[7; 100_000])?;
            Err(std::io::Error::other("the encoder gave up"))
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains(&path.display().to_string()) && e.contains("the encoder gave up"), "{e}");
        assert!(!path.exists() && !temp_path(&path).exists());
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0, "nothing is left in the folder");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_failed_write_keeps_the_previous_file() {
        let dir = temp_dir("keeps");
        let path = dir.join("out.json");
        write_bytes(&path, b"old").unwrap();
        assert!(write_atomically(&path, |w| w.write_all(b"new, half").and(Err(std::io::Error::other("x"))))
            .is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"old");
        write_bytes(&path, b"new").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new");
        assert!(!temp_path(&path).exists());
        // A missing folder is reported with the file's name.
        let e = write_bytes(&dir.join("no/such/folder.json"), b"x").unwrap_err().to_string();
        assert!(e.contains("folder.json") && e.contains("cannot write"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn a_full_disk_is_reported_naming_the_file() {
        // /dev/full fails every write with ENOSPC, as a full disk does; a symbolic link puts it
        // where the temporary file goes.
        let dir = temp_dir("full");
        let path = dir.join("image.png");
        std::os::unix::fs::symlink("/dev/full", temp_path(&path)).unwrap();
        let e = write_bytes(&path, &[1; 64 * 1024]).unwrap_err().to_string();
        assert!(e.contains("image.png") && e.contains("No space left on device"), "{e}");
        assert!(!path.exists());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
