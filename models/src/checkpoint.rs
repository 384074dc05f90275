//! Training checkpoints in safetensors: every parameter with its AdamW moments, the step, and a
//! JSON description of the run.
//!
//! Layout: tensor `param/<name>` holds a parameter, `adamw_m/<name>` and `adamw_v/<name>` its
//! moments, all f32 in the parameter's shape. The safetensors `__metadata__` holds `format`
//! (`velox-checkpoint`), `version` (`1`), `step` (AdamW steps taken) and `config` (a JSON
//! object chosen by the caller: the config name, hyperparameters and so on).
//!
//! Writes are atomic ([`velox_io::write_atomically`]): the file is written in full to
//! `.<file name>.tmp` in the same folder, flushed to disk, renamed over the target, and the
//! folder is flushed, so a crash leaves either the old checkpoint or the new one, never half of
//! one. Loads check every tensor's name, dtype, shape and values (all finite) against the store
//! before changing anything, and say what does not match.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors, View};
use velox_engine::{Error, FileOp, Precision, Result};

use crate::params::{LossScale, ParamStore};
pub use velox_io::temp_path;
use velox_io::write_bytes;

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
    /// The loss scale of an f16 training run when it was written.
    pub loss_scale: Option<LossScale>,
}

/// An f32 slice seen as a safetensors tensor.
pub(crate) struct F32View<'a> {
    pub shape: &'a [usize],
    pub data: &'a [f32],
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
    let mut meta = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("version".to_string(), VERSION.to_string()),
        ("step".to_string(), store.step().to_string()),
        ("config".to_string(), config.to_string()),
    ]);
    // The loss scale of f16 training, which a resumed run must start from to repeat the run.
    if store.training_precision() == Precision::F16 {
        let scale = serde_json::to_string(&store.loss_scale()).expect("plain data serialises");
        meta.insert("loss_scale".to_string(), scale);
    }
    let mut bytes = safetensors::serialize(tensors, Some(meta))
        .map_err(|e| Error::Invalid(format!("checkpoint {}: cannot serialise: {e}", path.display())))?;
    drop(host);
    canonical_header(&mut bytes);
    write_bytes(path, &bytes)
}

/// Rewrites a serialised file's JSON header with its keys in sorted order, in place: safetensors
/// writes the metadata map in hash order, which differs from process to process, and the same
/// state should give the same bytes (so a resumed run's checkpoint can be compared byte for byte
/// with an uninterrupted run's). The sorted header has the same characters, so the same length
/// and the same tensor offsets; should it not, the header stays as it was.
pub(crate) fn canonical_header(bytes: &mut [u8]) {
    let Some(len) = bytes.get(..8).map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")) as usize)
    else {
        return;
    };
    let Some(header) = bytes.get_mut(8..8 + len) else { return };
    // serde_json's map is a BTreeMap (no `preserve_order`), so it serialises keys sorted.
    let Ok(value) = serde_json::from_slice::<serde_json::Value>(header) else { return };
    let sorted = value.to_string();
    if sorted.len() <= header.len() {
        header[..sorted.len()].copy_from_slice(sorted.as_bytes());
        header[sorted.len()..].fill(b' ');
    }
}

/// The step and config a checkpoint holds, without loading its tensors (to build the model the
/// checkpoint fits before [`load`]).
pub fn peek(path: &Path) -> Result<CheckpointInfo> {
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, FileOp::Read, e))?;
    read_info(&bytes, path)
}

fn read_info(bytes: &[u8], path: &Path) -> Result<CheckpointInfo> {
    let (_, header) = SafeTensors::read_metadata(bytes)
        .map_err(|e| content(path, format!("the checkpoint is corrupt: {e}")))?;
    let meta = header.metadata().clone().unwrap_or_default();
    let field =
        |k: &str| meta.get(k).ok_or_else(|| content(path, format!("the checkpoint's metadata lacks {k:?}")));
    if field("format")? != FORMAT {
        return Err(content(
            path,
            format!("not a velox checkpoint (format {:?}, expected {FORMAT:?})", field("format")?),
        ));
    }
    if field("version")? != VERSION {
        return Err(content(
            path,
            format!("checkpoint version {}, this build reads version {VERSION}", field("version")?),
        ));
    }
    let step: u64 = field("step")?
        .parse()
        .map_err(|_| content(path, format!("the checkpoint's step {:?} is not a number", meta["step"])))?;
    let config = field("config")?.clone();
    let loss_scale = match meta.get("loss_scale") {
        None => None,
        Some(s) => Some(
            serde_json::from_str::<LossScale>(s)
                .ok()
                .filter(LossScale::valid)
                .ok_or_else(|| content(path, format!("the checkpoint's loss scale {s:?} is unreadable")))?,
        ),
    };
    Ok(CheckpointInfo { step, config, loss_scale })
}

fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::file(path, FileOp::Read, e))
}

/// A checkpoint whose bytes are not what a checkpoint of the model holds.
fn content(path: &Path, why: impl std::fmt::Display) -> Error {
    Error::file(path, FileOp::Content, why)
}

fn deserialize<'a>(bytes: &'a [u8], path: &Path) -> Result<SafeTensors<'a>> {
    SafeTensors::deserialize(bytes).map_err(|e| {
        content(path, format!("the checkpoint is corrupt or truncated ({} bytes): {e}", bytes.len()))
    })
}

/// A tensor's values, which must be f32.
fn f32_values(path: &Path, name: &str, t: &safetensors::tensor::TensorView<'_>) -> Result<Vec<f32>> {
    if t.dtype() != Dtype::F32 {
        return Err(content(path, format!("tensor {name:?} is {:?}, expected F32", t.dtype())));
    }
    Ok(t.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
}

/// Fails, naming the tensor and counting, where `values` hold a NaN or an Inf.
fn check_finite(path: &Path, step: u64, name: &str, values: &[f32]) -> Result<()> {
    let bad = values.iter().filter(|v| !v.is_finite()).count();
    if bad > 0 {
        return Err(content(
            path,
            format!(
                "(step {step}) tensor {name:?} holds {bad} NaN or Inf value(s) of {} (a diverged run or a \
                 damaged file)",
                values.len()
            ),
        ));
    }
    Ok(())
}

/// Every tensor of a checkpoint by name (f32 values in row-major order), with its metadata,
/// without a model to load it into (to inspect or compare checkpoints).
pub fn read_tensors(path: &Path) -> Result<(CheckpointInfo, BTreeMap<String, Vec<f32>>)> {
    let bytes = read_file(path)?;
    let file = deserialize(&bytes, path)?;
    let info = read_info(&bytes, path)?;
    let tensors =
        file.tensors().into_iter().map(|(name, t)| Ok((name.clone(), f32_values(path, &name, &t)?)));
    Ok((info, tensors.collect::<Result<_>>()?))
}

/// Checks that every value of a checkpoint (parameters and moments) is finite, and returns its
/// metadata; the error names the first tensor that holds a NaN or an Inf and how many it holds.
/// A run stopped by a NaN calls its checkpoint good only after this check.
pub fn verify_finite(path: &Path) -> Result<CheckpointInfo> {
    let (info, tensors) = read_tensors(path)?;
    for (name, values) in &tensors {
        check_finite(path, info.step, name, values)?;
    }
    Ok(info)
}

/// The checkpoint's tensors of the parts `parts` (prefixes of [`PARTS`]) laid out as the
/// store's flat buffers, one per part, every tensor checked first: missing, of another shape or
/// dtype, NaN or Inf, or a tensor the store does not have (of those parts, or of any name when
/// `parts` is all of them), each an error naming it.
fn read_parts(path: &Path, store: &ParamStore, parts: &[&str]) -> Result<(CheckpointInfo, Vec<Vec<f32>>)> {
    let bytes = read_file(path)?;
    let file = deserialize(&bytes, path)?;
    let info = read_info(&bytes, path)?;
    let total = store.flat_params().numel();
    let mut host = vec![vec![0f32; total]; parts.len()];
    let mut expected = std::collections::HashSet::new();
    for (prefix, flat) in parts.iter().zip(host.iter_mut()) {
        for p in store.infos() {
            let name = format!("{prefix}{}", p.name);
            let t = file.tensor(&name).map_err(|_| {
                content(path, format!("the checkpoint lacks tensor {name:?} (shape {:?})", p.shape))
            })?;
            if t.shape() != p.shape.as_slice() {
                return Err(content(
                    path,
                    format!("tensor {name:?} has shape {:?}, the model expects {:?}", t.shape(), p.shape),
                ));
            }
            let values = f32_values(path, &name, &t)?;
            check_finite(path, info.step, &name, &values)?;
            flat[p.offset..p.offset + p.numel].copy_from_slice(&values);
            expected.insert(name);
        }
    }
    let ours = |n: &str| parts.len() == PARTS.len() || parts.iter().any(|prefix| n.starts_with(prefix));
    if let Some(extra) = file.names().into_iter().find(|n| ours(n) && !expected.contains(*n)) {
        return Err(content(
            path,
            format!(
                "the checkpoint holds tensor {extra:?}, which the model does not have (a different config?)"
            ),
        ));
    }
    Ok((info, host))
}

/// Loads only the parameters of a checkpoint into `store` (to start a new run from another
/// run's weights): the moments and the step counter stay as they are. Every parameter tensor is
/// checked first (missing, unexpected, of another shape or dtype, NaN or Inf), the error names
/// it, and the store is left unchanged.
pub fn load_params(path: &Path, store: &mut ParamStore) -> Result<CheckpointInfo> {
    let (info, host) = read_parts(path, store, &PARTS[..1])?;
    store.flat_params().write(&host[0])?;
    Ok(info)
}

/// The JSON object a checkpoint describes its run with (see [`save`]'s `config`).
pub fn config_json(path: &Path) -> Result<serde_json::Value> {
    let info = peek(path)?;
    serde_json::from_str(&info.config)
        .map_err(|e| Error::Invalid(format!("checkpoint {}: config is not JSON: {e}", path.display())))
}

/// The config of a checkpoint that must hold a model of kind `kind` (its JSON's `model`; the
/// error names `what` the config should be).
pub fn model_config<C: serde::de::DeserializeOwned>(path: &Path, kind: &str, what: &str) -> Result<C> {
    let json = config_json(path)?;
    if json["model"] != kind {
        return Err(Error::Invalid(format!(
            "checkpoint {} holds a {}, not a {kind}",
            path.display(),
            json["model"]
        )));
    }
    serde_json::from_value(json["config"].clone()).map_err(|e| {
        Error::Invalid(format!("checkpoint {}: the {what}'s config is unreadable: {e}", path.display()))
    })
}

/// Loads a checkpoint written by [`save`] into `store` (parameters, moments and step) and
/// returns its metadata. Every tensor is checked first: a missing or unexpected tensor, a wrong
/// dtype or shape, a NaN or Inf in a parameter or moment, a truncated or corrupt file gives an
/// error naming it, and the store is left unchanged.
pub fn load(path: &Path, store: &mut ParamStore) -> Result<CheckpointInfo> {
    let (info, host) = read_parts(path, store, &PARTS)?;
    let (m, v) = store.moments();
    store.flat_params().write(&host[0])?;
    m.write(&host[1])?;
    v.write(&host[2])?;
    store.set_step(info.step);
    if let Some(scale) = info.loss_scale {
        *store.loss_scale_mut() = scale;
    }
    Ok(info)
}
