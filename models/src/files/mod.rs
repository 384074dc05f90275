//! File formats users see: Gaussians as PLY in the 3D Gaussian splatting layout ([`ply`]),
//! images as PNG and depth as EXR ([`image`]). Every reader names what is wrong with a bad
//! file; every writer writes a temporary beside the target and renames it over, so a failed
//! write never leaves half a file in place of a good one.

pub mod image;
pub mod ply;

use std::io::Write;
use std::path::Path;

use velox_engine::{Error, Result};

/// Writes `bytes` to `path` through a temporary file in the same folder.
pub(crate) fn write_atomically(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let name = path
        .file_name()
        .ok_or_else(|| Error::Invalid(format!("{}: not a file name", path.display())))?
        .to_string_lossy();
    let tmp = path.with_file_name(format!(".{name}.tmp"));
    let result = write(&tmp).and_then(|()| {
        std::fs::rename(&tmp, path)
            .map_err(|e| Error::Invalid(format!("renaming {} to {}: {e}", tmp.display(), path.display())))
    });
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Writes raw bytes atomically.
pub(crate) fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomically(path, |tmp| {
        let mut f = std::fs::File::create(tmp).map_err(|e| io_error(tmp, e))?;
        f.write_all(bytes).and_then(|()| f.sync_all()).map_err(|e| io_error(tmp, e))
    })
}

pub(crate) fn io_error(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::Invalid(format!("{}: {e}", path.display()))
}
