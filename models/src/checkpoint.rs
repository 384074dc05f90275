//! Training checkpoints in safetensors: every parameter with its AdamW moments, the step, and a
//! JSON description of the run.
//!
//! Layout: tensor `param/<name>` holds a parameter, `adamw_m/<name>` and `adamw_v/<name>` its
//! moments, all f32 in the parameter's shape. The safetensors `__metadata__` holds `format`
//! (`velox-checkpoint`), `version` (`1`), `step` (AdamW steps taken) and `config` (a JSON
//! object chosen by the caller: the config name, hyperparameters and so on).
//!
//! Weights files (`format` `velox-weights`) hold the parameters alone, as f16 or f32, with the
//! same `config` and `step`: what inference needs, a quarter of a checkpoint's size in f16.
//! [`save_weights`] splits one larger than a size limit into parts named
//! `NAME-00001-of-00003.safetensors` (each part's metadata says which it is); any part, or the
//! unsplit name, reads as the whole. They load wherever a model is loaded to run ([`load_model`]:
//! decode, encode, eval, `--init`), never to resume a run ([`load`] refuses them).
//!
//! Writes are atomic ([`velox_io::write_atomically`]): the file is written in full to
//! `.<file name>.tmp` in the same folder, flushed to disk, renamed over the target, and the
//! folder is flushed, so a crash leaves either the old checkpoint or the new one, never half of
//! one. Loads check every tensor's name, dtype, shape and values (all finite) against the store
//! before changing anything, and say what does not match.
//!
//! Tests: `tests/training/train_primitives.rs` (round trips, refusals, weights files),
//! `tests/data/fuzz.rs` (damaged files).

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors, View};
use velox_engine::{Error, FileOp, Precision, Result};

use crate::params::{LossScale, ParamStore};
pub use velox_io::temp_path;
use velox_io::write_bytes;

pub const FORMAT: &str = "velox-checkpoint";
pub const WEIGHTS_FORMAT: &str = "velox-weights";
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
    /// A weights file ([`WEIGHTS_FORMAT`]): parameters only, no optimiser moments.
    pub weights_only: bool,
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
    let files = read_files(path)?;
    read_info(&files[0].1, &files[0].0)
}

fn read_info(bytes: &[u8], path: &Path) -> Result<CheckpointInfo> {
    let (_, header) = SafeTensors::read_metadata(bytes)
        .map_err(|e| content(path, format!("the checkpoint is corrupt: {e}")))?;
    let meta = header.metadata().clone().unwrap_or_default();
    let field =
        |k: &str| meta.get(k).ok_or_else(|| content(path, format!("the checkpoint's metadata lacks {k:?}")));
    let weights_only = field("format")? == WEIGHTS_FORMAT;
    if field("format")? != FORMAT && !weights_only {
        return Err(content(
            path,
            format!(
                "not a velox checkpoint (format {:?}, expected {FORMAT:?} or {WEIGHTS_FORMAT:?})",
                field("format")?
            ),
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
    Ok(CheckpointInfo { step, config, loss_scale, weights_only })
}

/// `(stem, index, total)` of a part's file name `STEM-00001-of-00003.safetensors`.
fn part_name(path: &Path) -> Option<(String, usize, usize)> {
    let name = path.file_name()?.to_str()?.strip_suffix(".safetensors")?;
    let (rest, total) = name.rsplit_once("-of-")?;
    let (stem, index) = rest.rsplit_once('-')?;
    let digits = |s: &str| s.len() == 5 && s.bytes().all(|b| b.is_ascii_digit());
    if !(digits(index) && digits(total)) {
        return None;
    }
    Some((stem.to_string(), index.parse().ok()?, total.parse().ok()?))
}

fn part_path(folder: &Path, stem: &str, index: usize, total: usize) -> std::path::PathBuf {
    folder.join(format!("{stem}-{index:05}-of-{total:05}.safetensors"))
}

/// The bytes of the file at `path`, or of every part of a split weights file: `path` naming
/// one part, or the unsplit name `STEM.safetensors` where only its parts exist. Each part is
/// named by its path; a missing part is an error that names it.
fn read_files(path: &Path) -> Result<Vec<(std::path::PathBuf, Vec<u8>)>> {
    let folder = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let split = match part_name(path) {
        Some((stem, _, total)) => Some((stem, total)),
        None if !path.exists() => {
            // `STEM.safetensors` saved in parts: its first part says how many.
            let stem = path.file_name().and_then(|n| n.to_str()).and_then(|n| n.strip_suffix(".safetensors"));
            stem.and_then(|stem| {
                let prefix = format!("{stem}-00001-of-");
                let entries = std::fs::read_dir(&folder).ok()?;
                entries.filter_map(|e| e.ok()).find_map(|e| {
                    let p = e.path();
                    let n = p.file_name()?.to_str()?.to_string();
                    n.starts_with(&prefix).then(|| part_name(&p)).flatten().map(|(s, _, t)| (s, t))
                })
            })
        }
        None => None,
    };
    let Some((stem, total)) = split else {
        return Ok(vec![(
            path.to_path_buf(),
            std::fs::read(path).map_err(|e| Error::file(path, FileOp::Read, e))?,
        )]);
    };
    if total == 0 {
        return Err(content(path, "a weights file split into 0 parts"));
    }
    (1..=total)
        .map(|i| {
            let p = part_path(&folder, &stem, i, total);
            let bytes = std::fs::read(&p)
                .map_err(|e| Error::file(&p, FileOp::Read, format!("part {i} of {total}: {e}")))?;
            Ok((p, bytes))
        })
        .collect()
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

/// A tensor's values, which must be f32 (or f16, in a weights file: `f16_ok`).
fn f32_values(
    path: &Path,
    name: &str,
    t: &safetensors::tensor::TensorView<'_>,
    f16_ok: bool,
) -> Result<Vec<f32>> {
    match t.dtype() {
        Dtype::F32 => {
            Ok(t.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
        }
        Dtype::F16 if f16_ok => {
            Ok(t.data().chunks_exact(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect())
        }
        other => Err(content(
            path,
            format!("tensor {name:?} is {other:?}, expected F32{}", if f16_ok { " or F16" } else { "" }),
        )),
    }
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
    let files = read_files(path)?;
    let info = read_info(&files[0].1, &files[0].0)?;
    let mut out = BTreeMap::new();
    for (p, bytes) in &files {
        let file = deserialize(bytes, p)?;
        for (name, t) in file.tensors() {
            out.insert(name.clone(), f32_values(p, &name, &t, info.weights_only)?);
        }
    }
    Ok((info, out))
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
    let files = read_files(path)?;
    let info = read_info(&files[0].1, &files[0].0)?;
    let opened: Vec<(&Path, SafeTensors<'_>)> =
        files.iter().map(|(p, b)| Ok((p.as_path(), deserialize(b, p)?))).collect::<Result<_>>()?;
    if info.weights_only && parts.iter().any(|p| *p != PARTS[0]) {
        return Err(content(
            path,
            "holds weights only (no optimiser moments): decoding, encoding, evaluation and a run's \
             initial parameters take it, but a run cannot resume from it",
        ));
    }
    let total = store.flat_params().numel();
    let mut host = vec![vec![0f32; total]; parts.len()];
    let mut expected = std::collections::HashSet::new();
    for (prefix, flat) in parts.iter().zip(host.iter_mut()) {
        for p in store.infos() {
            let name = format!("{prefix}{}", p.name);
            let (file_path, t) =
                opened.iter().find_map(|(fp, f)| f.tensor(&name).ok().map(|t| (*fp, t))).ok_or_else(
                    || content(path, format!("the checkpoint lacks tensor {name:?} (shape {:?})", p.shape)),
                )?;
            if t.shape() != p.shape.as_slice() {
                return Err(content(
                    file_path,
                    format!("tensor {name:?} has shape {:?}, the model expects {:?}", t.shape(), p.shape),
                ));
            }
            let values = f32_values(file_path, &name, &t, info.weights_only)?;
            check_finite(file_path, info.step, &name, &values)?;
            flat[p.offset..p.offset + p.numel].copy_from_slice(&values);
            expected.insert(name);
        }
    }
    let ours = |n: &str| parts.len() == PARTS.len() || parts.iter().any(|prefix| n.starts_with(prefix));
    for (file_path, file) in &opened {
        if let Some(extra) = file.names().into_iter().find(|n| ours(n) && !expected.contains(*n)) {
            return Err(content(
                file_path,
                format!(
                    "the checkpoint holds tensor {extra:?}, which the model does not have (a different config?)"
                ),
            ));
        }
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

/// Loads what a model needs to run: a checkpoint's parameters, moments and step ([`load`]), or
/// a weights file's parameters and step (the moments stay as they are).
pub fn load_model(path: &Path, store: &mut ParamStore) -> Result<CheckpointInfo> {
    if !peek(path)?.weights_only {
        return load(path, store);
    }
    let (info, host) = read_parts(path, store, &PARTS[..1])?;
    store.flat_params().write(&host[0])?;
    store.set_step(info.step);
    Ok(info)
}

/// The number type of a weights file's tensors.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WeightsDtype {
    F16,
    F32,
}

/// An f16 slice seen as a safetensors tensor.
struct F16View<'a> {
    shape: &'a [usize],
    data: Vec<half::f16>,
}

impl View for F16View<'_> {
    fn dtype(&self) -> Dtype {
        Dtype::F16
    }
    fn shape(&self) -> &[usize] {
        self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Owned(self.data.iter().flat_map(|x| x.to_le_bytes()).collect())
    }
    fn data_len(&self) -> usize {
        self.data.len() * 2
    }
}

/// Writes the parameters of the checkpoint or weights file at `from` as a weights file at `to`
/// (config and step kept, the run's settings left out), in `dtype`, in parts of at most
/// `max_part_bytes` where the whole would be larger (each part holds whole tensors; a tensor
/// larger than the limit is refused by name). Returns the files written. A parameter whose f32
/// value is past f16's range is refused by name rather than written as an infinity.
pub fn save_weights(
    from: &Path,
    to: &Path,
    dtype: WeightsDtype,
    max_part_bytes: Option<u64>,
) -> Result<Vec<std::path::PathBuf>> {
    let (info, tensors) = read_tensors(from)?;
    let mut config: serde_json::Value = serde_json::from_str(&info.config)
        .map_err(|e| content(from, format!("the config is not JSON: {e}")))?;
    if let Some(c) = config.as_object_mut() {
        c.remove("run");
    }
    let params: Vec<(&String, &Vec<f32>)> = tensors.iter().filter(|(n, _)| n.starts_with(PARTS[0])).collect();
    if params.is_empty() {
        return Err(content(from, "holds no parameters"));
    }
    let (shapes, _) = read_shapes(from)?;
    let width = match dtype {
        WeightsDtype::F16 => 2,
        WeightsDtype::F32 => 4,
    };
    for (name, values) in &params {
        check_finite(from, info.step, name, values)?;
        if dtype == WeightsDtype::F16 {
            if let Some(v) = values.iter().find(|v| v.abs() > 65504.0) {
                return Err(content(
                    from,
                    format!("tensor {name:?} holds {v}, past f16's range: write it as f32"),
                ));
            }
        }
    }
    // Parts in the tensors' name order, each filled while it stays under the limit (the header's
    // size is allowed for at 256 bytes a tensor).
    let limit = max_part_bytes.unwrap_or(u64::MAX);
    let mut groups: Vec<Vec<usize>> = vec![Vec::new()];
    let mut used = 0u64;
    for (i, (name, values)) in params.iter().enumerate() {
        let bytes = values.len() as u64 * width + 256;
        if bytes + 4096 > limit {
            return Err(Error::Invalid(format!(
                "tensor {name:?} takes {bytes} bytes, more than a part of at most {limit} bytes holds"
            )));
        }
        if used + bytes + 4096 > limit && !groups.last().expect("one group").is_empty() {
            groups.push(Vec::new());
            used = 0;
        }
        used += bytes;
        groups.last_mut().expect("one group").push(i);
    }
    let total = groups.len();
    let folder = to.parent().map(Path::to_path_buf).unwrap_or_default();
    let stem =
        to.file_name().and_then(|n| n.to_str()).and_then(|n| n.strip_suffix(".safetensors")).ok_or_else(
            || Error::Invalid(format!("{}: a weights file's name ends in .safetensors", to.display())),
        )?;
    let mut written = Vec::new();
    for (part, members) in groups.iter().enumerate() {
        let mut meta = HashMap::from([
            ("format".to_string(), WEIGHTS_FORMAT.to_string()),
            ("version".to_string(), VERSION.to_string()),
            ("step".to_string(), info.step.to_string()),
            ("config".to_string(), config.to_string()),
            ("part".to_string(), format!("{}/{total}", part + 1)),
        ]);
        meta.insert("dtype".to_string(), if dtype == WeightsDtype::F16 { "f16" } else { "f32" }.to_string());
        let bytes = match dtype {
            WeightsDtype::F32 => {
                let views: Vec<(String, F32View<'_>)> = members
                    .iter()
                    .map(|&i| {
                        (params[i].0.clone(), F32View { shape: &shapes[params[i].0], data: params[i].1 })
                    })
                    .collect();
                safetensors::serialize(views, Some(meta))
            }
            WeightsDtype::F16 => {
                let views: Vec<(String, F16View<'_>)> = members
                    .iter()
                    .map(|&i| {
                        let data = params[i].1.iter().map(|&v| half::f16::from_f32(v)).collect();
                        (params[i].0.clone(), F16View { shape: &shapes[params[i].0], data })
                    })
                    .collect();
                safetensors::serialize(views, Some(meta))
            }
        };
        let mut bytes =
            bytes.map_err(|e| Error::Invalid(format!("weights {}: cannot serialise: {e}", to.display())))?;
        canonical_header(&mut bytes);
        let path = if total == 1 { to.to_path_buf() } else { part_path(&folder, stem, part + 1, total) };
        write_bytes(&path, &bytes)?;
        written.push(path);
    }
    Ok(written)
}

/// The shape of every tensor of the checkpoint or weights file at `path`, by name.
fn read_shapes(path: &Path) -> Result<(BTreeMap<String, Vec<usize>>, CheckpointInfo)> {
    let files = read_files(path)?;
    let info = read_info(&files[0].1, &files[0].0)?;
    let mut out = BTreeMap::new();
    for (p, bytes) in &files {
        for (name, t) in deserialize(bytes, p)?.tensors() {
            out.insert(name, t.shape().to_vec());
        }
    }
    Ok((out, info))
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
