//! Training checkpoints in safetensors: every parameter with its AdamW moments, the step, and a
//! JSON description of the run.
//!
//! Layout: tensor `param/<name>` holds a parameter, `adamw_m/<name>` and `adamw_v/<name>` its
//! moments, all f32 in the parameter's shape. The safetensors `__metadata__` holds `format`
//! (`velox-checkpoint`), `version` (`1`), `step` (AdamW steps taken) and `config` (a JSON
//! object chosen by the caller: the config name, hyperparameters and so on).
//!
//! Writes are atomic: the file is written in full to `.<file name>.tmp` in the same folder,
//! flushed to disk, renamed over the target, and the folder is flushed, so a crash leaves
//! either the old checkpoint or the new one, never half of one. Loads check every tensor's name,
//! dtype, shape and values (all finite) against the store before changing anything, and say
//! what does not match.

use std::borrow::Cow;
use std::collections::HashMap;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors, View};
use velox_engine::{Error, Result};

use crate::params::ParamStore;

pub const FORMAT: &str = "velox-checkpoint";
pub const VERSION: &str = "1";

/// Tensor-name prefixes of the three buffers.
const PARTS: [&str; 3] = ["param/", "adamw_m/", "adamw_v/"];

/// What a checkpoint says about itself besides the tensors.
#[derive(Clone, Debug, PartialEq)]
pub struct CheckpointInfo {
    /// AdamW steps taken when it was written.
    pub step: u64,
    /// The JSON the run stored (config name, hyperparameters...).
    pub config: String,
}

/// An f32 slice seen as a safetensors tensor.
struct F32View<'a> {
    shape: &'a [usize],
    data: &'a [f32],
}

impl View for F32View<'_> {
    fn dtype(&self) -> Dtype {
        Dtype::F32
    }
    fn shape(&self) -> &[usize] {
        self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        if cfg!(target_endian = "little") {
            Cow::Borrowed(bytemuck::cast_slice(self.data))
        } else {
            Cow::Owned(self.data.iter().flat_map(|x| x.to_le_bytes()).collect())
        }
    }
    fn data_len(&self) -> usize {
        self.data.len() * 4
    }
}

/// Writes the store's parameters, moments and step to `path` atomically, with `config` (a JSON
/// object describing the run) in the metadata.
pub fn save(path: &Path, store: &ParamStore, config: &str) -> Result<()> {
    if !serde_json::from_str::<serde_json::Value>(config).is_ok_and(|v| v.is_object()) {
        return Err(Error::Invalid(format!("checkpoint config must be a JSON object, got {config:?}")));
    }
    let (m, v) = store.moments();
    let host: [Vec<f32>; 3] = [store.flat_params().read()?, m.read()?, v.read()?];
    let mut tensors = Vec::with_capacity(3 * store.len());
    for (prefix, flat) in PARTS.iter().zip(&host) {
        for p in store.infos() {
            let view = F32View { shape: &p.shape, data: &flat[p.offset..p.offset + p.numel] };
            tensors.push((format!("{prefix}{}", p.name), view));
        }
    }
    let meta = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("version".to_string(), VERSION.to_string()),
        ("step".to_string(), store.step().to_string()),
        ("config".to_string(), config.to_string()),
    ]);
    let bytes = safetensors::serialize(tensors, Some(meta))
        .map_err(|e| Error::Invalid(format!("checkpoint {}: cannot serialise: {e}", path.display())))?;
    drop(host);
    write_atomic(path, &bytes)
        .map_err(|e| Error::Invalid(format!("cannot write checkpoint {}: {e}", path.display())))
}

/// The temporary file a save of `path` writes before renaming it over `path`.
pub fn temp_path(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp"))
}

/// Writes `bytes` to `path` so that a crash leaves the old file or the new one: a temporary file
/// in the same folder (same file system, so the rename is atomic), fsync, rename, fsync of the
/// folder so the rename itself is durable.
fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    if path.file_name().is_none() {
        return Err(std::io::Error::new(std::io::ErrorKind::InvalidInput, "the path names no file"));
    }
    let tmp = temp_path(path);
    let written = (|| {
        let mut f = File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = written {
        // Only a file of ours is removed; a folder in its place is left as it is.
        if tmp.is_file() {
            let _ = std::fs::remove_file(&tmp);
        }
        return Err(e);
    }
    sync_dir(path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")))
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

/// The step and config a checkpoint holds, without loading its tensors (to build the model the
/// checkpoint fits before [`load`]).
pub fn peek(path: &Path) -> Result<CheckpointInfo> {
    let bytes = std::fs::read(path)
        .map_err(|e| Error::Invalid(format!("cannot read checkpoint {}: {e}", path.display())))?;
    read_info(&bytes, path)
}

fn read_info(bytes: &[u8], path: &Path) -> Result<CheckpointInfo> {
    let shown = path.display();
    let (_, header) = SafeTensors::read_metadata(bytes)
        .map_err(|e| Error::Invalid(format!("checkpoint {shown} is corrupt: {e}")))?;
    let meta = header.metadata().clone().unwrap_or_default();
    let field = |k: &str| {
        meta.get(k).ok_or_else(|| Error::Invalid(format!("checkpoint {shown}: metadata lacks {k:?}")))
    };
    if field("format")? != FORMAT {
        return Err(Error::Invalid(format!(
            "{shown} is not a velox checkpoint (format {:?}, expected {FORMAT:?})",
            field("format")?
        )));
    }
    if field("version")? != VERSION {
        return Err(Error::Invalid(format!(
            "checkpoint {shown} has version {}, this build reads version {VERSION}",
            field("version")?
        )));
    }
    let step: u64 = field("step")?.parse().map_err(|_| {
        Error::Invalid(format!("checkpoint {shown}: step {:?} is not a number", meta["step"]))
    })?;
    let config = field("config")?.clone();
    Ok(CheckpointInfo { step, config })
}

/// Loads a checkpoint written by [`save`] into `store` (parameters, moments and step) and
/// returns its metadata. Every tensor is checked first: a missing or unexpected tensor, a wrong
/// dtype or shape, a NaN or Inf in a parameter or moment, a truncated or corrupt file gives an
/// error naming it, and the store is left unchanged.
pub fn load(path: &Path, store: &mut ParamStore) -> Result<CheckpointInfo> {
    let shown = path.display();
    let bytes =
        std::fs::read(path).map_err(|e| Error::Invalid(format!("cannot read checkpoint {shown}: {e}")))?;
    let file = SafeTensors::deserialize(&bytes).map_err(|e| {
        Error::Invalid(format!("checkpoint {shown} is corrupt or truncated ({} bytes): {e}", bytes.len()))
    })?;
    let CheckpointInfo { step, config } = read_info(&bytes, path)?;

    let total = store.flat_params().numel();
    let mut host = [vec![0f32; total], vec![0f32; total], vec![0f32; total]];
    let mut expected = std::collections::HashSet::new();
    for (prefix, flat) in PARTS.iter().zip(host.iter_mut()) {
        for p in store.infos() {
            let name = format!("{prefix}{}", p.name);
            let t = file.tensor(&name).map_err(|_| {
                Error::Invalid(format!("checkpoint {shown} lacks tensor {name:?} (shape {:?})", p.shape))
            })?;
            if t.dtype() != Dtype::F32 {
                return Err(Error::Invalid(format!(
                    "checkpoint {shown}: tensor {name:?} is {:?}, expected F32",
                    t.dtype()
                )));
            }
            if t.shape() != p.shape.as_slice() {
                return Err(Error::Invalid(format!(
                    "checkpoint {shown}: tensor {name:?} has shape {:?}, the model expects {:?}",
                    t.shape(),
                    p.shape
                )));
            }
            let out = &mut flat[p.offset..p.offset + p.numel];
            for (o, b) in out.iter_mut().zip(t.data().chunks_exact(4)) {
                *o = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            }
            let bad = out.iter().filter(|x| !x.is_finite()).count();
            if bad > 0 {
                return Err(Error::Invalid(format!(
                    "checkpoint {shown}: tensor {name:?} holds {bad} non-finite value(s) (NaN or Inf) of {} (a diverged run or a damaged file)",
                    p.numel
                )));
            }
            expected.insert(name);
        }
    }
    if let Some(extra) = file.names().into_iter().find(|n| !expected.contains(*n)) {
        return Err(Error::Invalid(format!(
            "checkpoint {shown} holds tensor {extra:?}, which the model does not have (a different config?)"
        )));
    }
    let (m, v) = store.moments();
    store.flat_params().write(&host[0])?;
    m.write(&host[1])?;
    v.write(&host[2])?;
    store.set_step(step);
    Ok(CheckpointInfo { step, config })
}
