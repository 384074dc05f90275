//! The token store: a trained encoder's tokens of every scene of a dataset, encoded once
//! (`velox encode`), so that the models downstream of the encoder (voxel decoder, tracker,
//! generators) train on stored tokens with the encoder frozen.
//!
//! A token folder (by default `DATASET/tokens`, beside the scenes):
//! ```text
//! tokens.json          the manifest (TokenManifest), JSON:
//!                        format "velox-tokens", version 1,
//!                        origin: {checkpoint, checkpoint_hash, config, seed, precision},
//!                        tokens (k) and token_dim,
//!                        scenes: the scene names, in the dataset's order,
//!                        mean, std: per channel over every token of every scene, f64
//! SCENE.safetensors    one per scene of the manifest:
//!                        tensor `tokens`       f32 [k, token_dim], the encoder's output s
//!                        tensor `query_points` f32 [k, 4], x y z tau of each token's query
//!                        metadata: format, version, scene, checkpoint, checkpoint_hash,
//!                        config (the autoencoder config as JSON), seed, precision
//! ```
//!
//! - **Query points hold raw tau** (frame / 100, the cloud's own), not the encoder's
//!   `tau * time_scale`: they are the cloud's rows at the encoder layout's query indices
//!   (`EncoderCache.layout.queries`), copied bit for bit, so they mean the same whatever the
//!   config; the encoder's 4D position of a token is (x, y, z, tau * `config.encoder.time_scale`).
//! - **The origin** ([`TokenOrigin`]) names the encoder: the checkpoint's path (absolute, as it
//!   was encoded from) and a 64-bit FNV-1a hash of the checkpoint file's bytes, 16 lowercase
//!   hex digits ([`checkpoint_hash`]); the autoencoder config, the seed of the encoder's
//!   queries and the precision it ran in. Every scene file repeats the manifest's origin, and a
//!   file whose origin differs from its manifest's is refused.
//! - **The checkpoint must not have changed** ([`check_checkpoint`]): when the caller names a
//!   checkpoint, its hash must be the recorded one (whatever now lies at the recorded path);
//!   when it names none, the file at the recorded path must have the recorded hash. When the
//!   caller names none and the recorded checkpoint is gone, the tokens are accepted with a note
//!   that they could not be checked ([`CheckpointCheck::Unchecked`]); with a checkpoint named
//!   they are always checked against it.
//! - **Statistics**: the mean and the population standard deviation (divided by N) of each
//!   channel over the k rows of every scene, in f64 ([`TokenStats`]): each scene's two-pass
//!   mean and sum of squared deviations, merged in scene order (Chan, Golub and LeVeque), so
//!   the figures do not depend on which scenes a run encoded and which it found stored. The
//!   generators normalise the tokens by them.
//!
//! Files are written atomically ([`velox_io::write_bytes`]), safetensors headers with
//! their keys sorted, so the same tokens give the same bytes. Every reader checks everything
//! before returning (shapes, dtypes, finite values and ranges, the scene names, the hash's
//! form, the config) and names the file and the problem.
//!
//! Tests: `tests/data/tokens.rs` (the store, its statistics and refusals) and `tests/data/fuzz.rs`
//! (its files).

use std::collections::{BTreeSet, HashMap};
use std::io::Read;
use std::path::{Path, PathBuf};

use safetensors::tensor::{Dtype, SafeTensors};
use serde::{Deserialize, Serialize};
use velox_engine::{Error, Gpu, Precision, Result, Tensor};

use crate::checkpoint::{canonical_header, F32View};
use crate::config::AutoencoderConfig;
use velox_io::cloud::SLACK;
use velox_io::write_bytes;

pub const FORMAT: &str = "velox-tokens";
pub const VERSION: u32 = 1;
/// The manifest's file name in a token folder.
pub const MANIFEST: &str = "tokens.json";
/// The token folder's name inside a dataset when `velox encode` is not told another.
pub const DEFAULT_DIR: &str = "tokens";

/// Which cloud of a scene tokens encode.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CloudSource {
    /// `points.ply`: the input views' cloud, what the autoencoder encodes.
    #[default]
    Points,
    /// The scene's RGBD video back-projected (`velox_data::rgbd`): the tracking task's input.
    Video,
}

impl CloudSource {
    pub fn name(self) -> &'static str {
        match self {
            CloudSource::Points => "points",
            CloudSource::Video => "video",
        }
    }

    /// The token folder's name inside a dataset when `velox encode` is not told another:
    /// `tokens`, or `tokens-video`.
    pub fn default_dir(self) -> &'static str {
        match self {
            CloudSource::Points => DEFAULT_DIR,
            CloudSource::Video => "tokens-video",
        }
    }
}
/// Columns of a query point: x, y, z, tau.
pub const POINT_COLUMNS: usize = 4;

/// The 64-bit FNV-1a hash, fed in pieces.
#[derive(Clone, Copy, Debug)]
pub struct Fnv1a(u64);

impl Default for Fnv1a {
    fn default() -> Fnv1a {
        Fnv1a::new()
    }
}

impl Fnv1a {
    const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
    const PRIME: u64 = 0x0000_0100_0000_01b3;

    pub fn new() -> Fnv1a {
        Fnv1a(Self::OFFSET)
    }

    pub fn update(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ b as u64).wrapping_mul(Self::PRIME);
        }
    }

    pub fn finish(&self) -> u64 {
        self.0
    }
}

/// A hash as the token store writes it: 16 lowercase hex digits.
pub fn hash_hex(hash: u64) -> String {
    format!("{hash:016x}")
}

/// Whether `s` is a hash as [`hash_hex`] writes it; the error says what it is not.
fn check_hash(s: &str) -> std::result::Result<(), String> {
    if s.len() == 16 && s.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)) {
        Ok(())
    } else {
        Err(format!("checkpoint_hash {s:?} is not 16 lowercase hex digits (a 64-bit FNV-1a hash)"))
    }
}

/// The 64-bit FNV-1a hash of a file's bytes, as [`hash_hex`] writes it (read in pieces, so a
/// checkpoint of any size takes little memory).
pub fn checkpoint_hash(path: &Path) -> Result<String> {
    let failed = |e: std::io::Error| Error::file(path, velox_engine::FileOp::Read, e);
    let mut file = std::fs::File::open(path).map_err(failed)?;
    let mut hash = Fnv1a::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        match file.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => hash.update(&buf[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(failed(e)),
        }
    }
    Ok(hash_hex(hash.finish()))
}

/// Fails unless `autoencoder` (a checkpoint file) hashes to `trained_on`, the autoencoder
/// whose tokens a downstream model (`what`) trained on, when it recorded one.
pub fn check_encoder(trained_on: Option<&str>, autoencoder: &Path, what: &str) -> Result<()> {
    let Some(want) = trained_on else { return Ok(()) };
    let got = checkpoint_hash(autoencoder)?;
    if want != got {
        return Err(Error::Invalid(format!(
            "the {what} trained on the tokens of an autoencoder checkpoint of hash {want}; {} has hash {got} \
             (its tokens would mean something else to the {what})",
            autoencoder.display()
        )));
    }
    Ok(())
}

/// The token count `k` of a scene's tokens for a downstream model (`what`) that reads tokens
/// `token_dim` wide: they must be `[k > 0, token_dim]`.
pub fn check_shape(what: &str, tokens: &Tensor, token_dim: usize) -> Result<usize> {
    match tokens.shape() {
        &[k, d] if k > 0 && d == token_dim => Ok(k),
        _ => Err(Error::Shape(format!(
            "{what}: tokens must be [k > 0, {token_dim}] (the config's token_dim), got {tokens:?}"
        ))),
    }
}

/// Checks a scene name as a token folder uses it (a file name: `NAME.safetensors`).
pub fn check_scene_name(name: &str) -> std::result::Result<(), String> {
    let bad = name.is_empty()
        || name.starts_with('.')
        || name.len() > 200
        || name.chars().any(|c| c == '/' || c == '\\' || c.is_control());
    if bad {
        return Err(format!(
            "scene name {name:?} is not a folder name (non-empty, at most 200 bytes, no leading dot, \
             no slash or control character)"
        ));
    }
    Ok(())
}

/// Where a folder's tokens come from: the same in the manifest and every scene file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenOrigin {
    /// The autoencoder checkpoint the tokens were encoded with (absolute).
    pub checkpoint: PathBuf,
    /// Its FNV-1a hash ([`checkpoint_hash`]).
    pub checkpoint_hash: String,
    /// Its config.
    pub config: AutoencoderConfig,
    /// Seed of the encoder's queries (`Autoencoder::encode`).
    pub seed: u64,
    /// The precision the encoder ran in.
    #[serde(with = "crate::run::precision_name")]
    pub precision: Precision,
    /// The cloud encoded; folders written before there was a choice read `points`.
    #[serde(default)]
    pub source: CloudSource,
}

impl TokenOrigin {
    /// Checks the hash's form and the config; `file` names the file for the error.
    fn check(&self, file: &Path) -> Result<()> {
        let invalid = |why: String| Error::Invalid(format!("{}: {why}", file.display()));
        check_hash(&self.checkpoint_hash).map_err(invalid)?;
        if self.checkpoint.as_os_str().is_empty() {
            return Err(invalid("the checkpoint's path is empty".into()));
        }
        self.config.validate().map_err(|e| invalid(format!("config: {}", message(e))))
    }

    /// The sizes of a scene's tokens under this origin: (k, token_dim).
    pub fn shape(&self) -> (usize, usize) {
        (self.config.encoder.tokens, self.config.encoder.token_dim)
    }

    /// What differs from `other`, in words ("seed 1, not 2"; empty when nothing does).
    pub fn differences(&self, other: &TokenOrigin) -> Vec<String> {
        let mut out = Vec::new();
        if self.checkpoint_hash != other.checkpoint_hash && self.checkpoint == other.checkpoint {
            out.push(format!(
                "checkpoint {} with hash {}, not {}",
                self.checkpoint.display(),
                self.checkpoint_hash,
                other.checkpoint_hash
            ));
        } else if self.checkpoint_hash != other.checkpoint_hash {
            out.push(format!(
                "checkpoint {} (hash {}), not {} (hash {})",
                self.checkpoint.display(),
                self.checkpoint_hash,
                other.checkpoint.display(),
                other.checkpoint_hash
            ));
        } else if self.config != other.config {
            out.push("the same checkpoint hash with another config".into());
        }
        if self.seed != other.seed {
            out.push(format!("seed {}, not {}", self.seed, other.seed));
        }
        if self.precision != other.precision {
            out.push(format!("precision {}, not {}", self.precision.name(), other.precision.name()));
        }
        if self.source != other.source {
            out.push(format!("the {} cloud, not the {}", self.source.name(), other.source.name()));
        }
        out
    }
}

/// The message of an engine error without its kind.
fn message(e: Error) -> String {
    match e {
        Error::Invalid(why) => why,
        other => other.to_string(),
    }
}

/// One scene's stored tokens.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneTokens {
    pub scene: String,
    /// `[k, token_dim]`, row-major.
    pub tokens: Vec<f32>,
    /// `[k, 4]`: x, y, z, tau of the cloud point each token's query is.
    pub query_points: Vec<f32>,
    pub token_dim: usize,
}

impl SceneTokens {
    /// Checks the scene's name, the shapes (k >= 1 rows of `token_dim >= 1` tokens and of 4
    /// query columns), that every value is finite and the query points lie where cloud points
    /// may (xyz in [-1, 1]^3, tau >= 0).
    pub fn new(
        scene: &str,
        tokens: Vec<f32>,
        query_points: Vec<f32>,
        token_dim: usize,
    ) -> Result<SceneTokens> {
        let t = SceneTokens { scene: scene.to_string(), tokens, query_points, token_dim };
        t.check().map_err(|why| Error::Invalid(format!("tokens of scene {scene:?}: {why}")))?;
        Ok(t)
    }

    fn check(&self) -> std::result::Result<(), String> {
        check_scene_name(&self.scene)?;
        let d = self.token_dim;
        if d == 0 || self.tokens.is_empty() || !self.tokens.len().is_multiple_of(d) {
            return Err(format!("{} token values are not k >= 1 rows of {d} channels", self.tokens.len()));
        }
        let k = self.tokens.len() / d;
        if self.query_points.len() != k * POINT_COLUMNS {
            return Err(format!(
                "{} query-point values for {k} tokens, expected {k} rows of x, y, z, tau",
                self.query_points.len()
            ));
        }
        if let Some(i) = self.tokens.iter().position(|v| !v.is_finite()) {
            return Err(format!("token {} channel {} is {}", i / d, i % d, self.tokens[i]));
        }
        for (i, p) in self.query_points.chunks_exact(POINT_COLUMNS).enumerate() {
            let inside = p.iter().all(|v| v.is_finite()) && p[..3].iter().all(|v| v.abs() <= 1.0 + SLACK);
            if !inside || p[3] < 0.0 {
                return Err(format!(
                    "query point {i} is {p:?}, not x, y, z in [-1, 1] and a frame time tau >= 0"
                ));
            }
        }
        Ok(())
    }

    /// k: the tokens of the scene.
    pub fn k(&self) -> usize {
        self.tokens.len() / self.token_dim
    }

    /// The tokens on the device, f32 `[k, token_dim]`.
    pub fn upload(&self, gpu: &Gpu) -> Result<Tensor> {
        Tensor::from_slice(gpu, &[self.k(), self.token_dim], &self.tokens)
    }
}

/// The file of scene `scene` in the token folder `dir`.
pub fn scene_file(dir: &Path, scene: &str) -> PathBuf {
    dir.join(format!("{scene}.safetensors"))
}

/// Writes a scene's tokens to `dir/SCENE.safetensors` (atomically) with `origin` in its
/// metadata; returns the path. The tokens must have the origin's shape.
pub fn write_scene_file(dir: &Path, origin: &TokenOrigin, tokens: &SceneTokens) -> Result<PathBuf> {
    let path = scene_file(dir, &tokens.scene);
    let (k, d) = origin.shape();
    if (tokens.k(), tokens.token_dim) != (k, d) {
        return Err(Error::Shape(format!(
            "{}: tokens [{}, {}], the origin's config makes [{k}, {d}]",
            path.display(),
            tokens.k(),
            tokens.token_dim
        )));
    }
    let checkpoint = origin.checkpoint.to_str().ok_or_else(|| {
        Error::Invalid(format!(
            "{}: the checkpoint's path {:?} is not UTF-8",
            path.display(),
            origin.checkpoint
        ))
    })?;
    let meta = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("version".to_string(), VERSION.to_string()),
        ("scene".to_string(), tokens.scene.clone()),
        ("checkpoint".to_string(), checkpoint.to_string()),
        ("checkpoint_hash".to_string(), origin.checkpoint_hash.clone()),
        ("config".to_string(), serde_json::to_string(&origin.config).expect("a config serialises")),
        ("seed".to_string(), origin.seed.to_string()),
        ("precision".to_string(), origin.precision.name().to_string()),
        ("source".to_string(), origin.source.name().to_string()),
    ]);
    let (token_shape, point_shape) = ([k, d], [k, POINT_COLUMNS]);
    let tensors = [
        ("tokens".to_string(), F32View { shape: &token_shape, data: &tokens.tokens }),
        ("query_points".to_string(), F32View { shape: &point_shape, data: &tokens.query_points }),
    ];
    let mut bytes = safetensors::serialize(tensors, Some(meta))
        .map_err(|e| Error::Invalid(format!("{}: cannot serialise: {e}", path.display())))?;
    canonical_header(&mut bytes);
    write_bytes(&path, &bytes)?;
    Ok(path)
}

/// Reads and checks a scene file on its own: the safetensors layout (exactly `tokens` and
/// `query_points`, f32, of shapes `[k, d]` and `[k, 4]`), the values ([`SceneTokens::new`]),
/// the metadata (format, version, a scene name that is the file's, the origin's hash and
/// config, tokens of the config's shape). Every error names the file.
pub fn read_scene_file(path: &Path) -> Result<(TokenOrigin, SceneTokens)> {
    let shown = path.display();
    let invalid = |why: String| Error::Invalid(format!("{shown}: {why}"));
    let bytes = std::fs::read(path).map_err(|e| invalid(format!("cannot read the tokens: {e}")))?;
    let file = SafeTensors::deserialize(&bytes)
        .map_err(|e| invalid(format!("not a safetensors file, or truncated ({} bytes): {e}", bytes.len())))?;
    let (_, header) =
        SafeTensors::read_metadata(&bytes).map_err(|e| invalid(format!("unreadable header: {e}")))?;
    let meta = header.metadata().clone().unwrap_or_default();
    let field = |k: &str| meta.get(k).ok_or_else(|| invalid(format!("the metadata lacks {k:?}")));
    if field("format")? != FORMAT {
        return Err(invalid(format!("format {:?}, expected {FORMAT:?}", field("format")?)));
    }
    if field("version")? != &VERSION.to_string() {
        return Err(invalid(format!("version {:?}, this build reads version {VERSION}", field("version")?)));
    }
    let scene = field("scene")?.clone();
    check_scene_name(&scene).map_err(invalid)?;
    let expected = format!("{scene}.safetensors");
    if path.file_name().is_none_or(|n| n != expected.as_str()) {
        return Err(invalid(format!("the tokens of scene {scene:?} belong in a file named {expected}")));
    }
    let config: AutoencoderConfig = serde_json::from_str(field("config")?)
        .map_err(|e| invalid(format!("config is not an autoencoder config: {e}")))?;
    let seed =
        field("seed")?.parse().map_err(|_| invalid(format!("seed {:?} is not a u64", meta["seed"])))?;
    let precision = crate::run::precision_name::parse(field("precision")?)
        .ok_or_else(|| invalid(format!("precision {:?} is not f32 or f16", meta["precision"])))?;
    let source = match meta.get("source").map(String::as_str) {
        None | Some("points") => CloudSource::Points,
        Some("video") => CloudSource::Video,
        Some(other) => return Err(invalid(format!("source {other:?} is not points or video"))),
    };
    let origin = TokenOrigin {
        checkpoint: PathBuf::from(field("checkpoint")?),
        checkpoint_hash: field("checkpoint_hash")?.clone(),
        config,
        seed,
        precision,
        source,
    };
    origin.check(path)?;

    if file.len() != 2 {
        let names: BTreeSet<&str> = file.names().into_iter().collect();
        return Err(invalid(format!("holds tensors {names:?}, expected exactly tokens and query_points")));
    }
    let tensor = |name: &str| -> Result<(Vec<usize>, Vec<f32>)> {
        let t = file.tensor(name).map_err(|_| invalid(format!("lacks tensor {name:?}")))?;
        if t.dtype() != Dtype::F32 {
            return Err(invalid(format!("tensor {name:?} is {:?}, expected F32", t.dtype())));
        }
        let values = t.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        Ok((t.shape().to_vec(), values))
    };
    let (token_shape, tokens) = tensor("tokens")?;
    let (point_shape, query_points) = tensor("query_points")?;
    let (k, d) = origin.shape();
    if token_shape != [k, d] || point_shape != [k, POINT_COLUMNS] {
        return Err(invalid(format!(
            "tensors tokens {token_shape:?} and query_points {point_shape:?}, the config makes [{k}, {d}] and \
             [{k}, {POINT_COLUMNS}]"
        )));
    }
    let tokens = SceneTokens::new(&scene, tokens, query_points, d).map_err(|e| invalid(message(e)))?;
    Ok((origin, tokens))
}

/// Per-channel count, mean and sum of squared deviations of tokens; merged in a fixed order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TokenStats {
    count: u64,
    mean: Vec<f64>,
    m2: Vec<f64>,
}

impl TokenStats {
    /// The statistics of rows of `token_dim` channels (two passes in f64).
    pub fn of(tokens: &[f32], token_dim: usize) -> TokenStats {
        if token_dim == 0 {
            return TokenStats::default();
        }
        let rows = tokens.len() / token_dim;
        let mut mean = vec![0f64; token_dim];
        for row in tokens.chunks_exact(token_dim) {
            for (m, &v) in mean.iter_mut().zip(row) {
                *m += v as f64;
            }
        }
        mean.iter_mut().for_each(|m| *m /= rows.max(1) as f64);
        let mut m2 = vec![0f64; token_dim];
        for row in tokens.chunks_exact(token_dim) {
            for ((s, &m), &v) in m2.iter_mut().zip(&mean).zip(row) {
                *s += (v as f64 - m) * (v as f64 - m);
            }
        }
        TokenStats { count: rows as u64, mean, m2 }
    }

    /// Adds `other`'s rows (after this one's), by the pairwise update of Chan, Golub and
    /// LeVeque.
    pub fn merge(&mut self, other: &TokenStats) {
        if other.count == 0 {
            return;
        }
        if self.count == 0 {
            *self = other.clone();
            return;
        }
        let (na, nb) = (self.count as f64, other.count as f64);
        let n = na + nb;
        for ((ma, sa), (&mb, &sb)) in
            self.mean.iter_mut().zip(&mut self.m2).zip(other.mean.iter().zip(&other.m2))
        {
            let delta = mb - *ma;
            *ma += delta * nb / n;
            *sa += sb + delta * delta * na * nb / n;
        }
        self.count += other.count;
    }

    /// Rows counted.
    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn mean(&self) -> &[f64] {
        &self.mean
    }

    /// The population standard deviation (divided by the count) of each channel.
    pub fn std(&self) -> Vec<f64> {
        self.m2.iter().map(|s| (s / self.count.max(1) as f64).sqrt()).collect()
    }
}

/// A token folder's `tokens.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenManifest {
    pub format: String,
    pub version: u32,
    pub origin: TokenOrigin,
    /// k, and the channels of a token.
    pub tokens: usize,
    pub token_dim: usize,
    /// The scenes, in the dataset's order; each has `NAME.safetensors` in the folder.
    pub scenes: Vec<String>,
    /// Per channel over every token of every scene: the mean and the population standard
    /// deviation.
    #[serde(deserialize_with = "exact_f64s")]
    pub mean: Vec<f64>,
    #[serde(deserialize_with = "exact_f64s")]
    pub std: Vec<f64>,
}

/// A JSON array of numbers read by Rust's own f64 parser, which rounds correctly: serde_json's
/// default parser can miss the last bit (0.0017168435151688757 came back as ...755), and the
/// statistics should read back as they were written. (serde_json's `float_roundtrip` would do
/// it too, but for every reader of the program: it makes 1e999 an error where the readers now
/// take it as an infinity and name the field.)
fn exact_f64s<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Vec<f64>, D::Error> {
    let raw = Vec::<Box<serde_json::value::RawValue>>::deserialize(d)?;
    raw.iter()
        .map(|r| {
            r.get()
                .parse::<f64>()
                .map_err(|_| serde::de::Error::custom(format!("{} is not a number", r.get())))
        })
        .collect()
}

impl TokenManifest {
    /// The manifest of `scenes` encoded under `origin`, with their statistics.
    pub fn new(origin: TokenOrigin, scenes: Vec<String>, stats: &TokenStats) -> TokenManifest {
        let (tokens, token_dim) = origin.shape();
        TokenManifest {
            format: FORMAT.into(),
            version: VERSION,
            origin,
            tokens,
            token_dim,
            scenes,
            mean: stats.mean().to_vec(),
            std: stats.std(),
        }
    }

    /// Reads and checks `dir/tokens.json`: format and version, the origin (hash, config), k
    /// and token_dim those of the config, at least one scene, each a valid name and listed
    /// once, a finite mean and a finite non-negative standard deviation per channel. Errors
    /// name the file.
    pub fn read(dir: &Path) -> Result<TokenManifest> {
        let path = dir.join(MANIFEST);
        let invalid = |why: String| Error::Invalid(format!("{}: {why}", path.display()));
        let text = std::fs::read_to_string(&path).map_err(|e| {
            invalid(format!("cannot read the token manifest ({e}); make the tokens with `velox encode`"))
        })?;
        let m: TokenManifest = serde_json::from_str(&text).map_err(|e| invalid(e.to_string()))?;
        if m.format != FORMAT || m.version != VERSION {
            return Err(invalid(format!(
                "format {:?} version {}, this build reads {FORMAT:?} version {VERSION}",
                m.format, m.version
            )));
        }
        m.origin.check(&path)?;
        let (k, d) = m.origin.shape();
        if (m.tokens, m.token_dim) != (k, d) {
            return Err(invalid(format!(
                "tokens {} and token_dim {}, but the config makes {k} tokens of {d}",
                m.tokens, m.token_dim
            )));
        }
        if m.scenes.is_empty() {
            return Err(invalid("lists no scenes".into()));
        }
        let mut seen = BTreeSet::new();
        for s in &m.scenes {
            check_scene_name(s).map_err(invalid)?;
            if !seen.insert(s) {
                return Err(invalid(format!("lists scene {s:?} twice")));
            }
        }
        for (name, v) in [("mean", &m.mean), ("std", &m.std)] {
            if v.len() != d {
                return Err(invalid(format!("{name} has {} channels, token_dim is {d}", v.len())));
            }
            if let Some(c) = v.iter().position(|x| !x.is_finite() || (name == "std" && *x < 0.0)) {
                return Err(invalid(format!("{name} of channel {c} is {}", v[c])));
            }
        }
        Ok(m)
    }

    /// Writes `dir/tokens.json` (atomically).
    pub fn write(&self, dir: &Path) -> Result<()> {
        let text = serde_json::to_string_pretty(self).map_err(|e| {
            Error::Invalid(format!("{}: cannot serialise the manifest: {e}", dir.join(MANIFEST).display()))
        })?;
        write_bytes(&dir.join(MANIFEST), (text + "\n").as_bytes())
    }
}

/// What [`check_checkpoint`] found.
#[derive(Clone, Debug, PartialEq)]
pub enum CheckpointCheck {
    /// The checkpoint at this path has the recorded hash.
    Verified(PathBuf),
    /// No checkpoint was named and the recorded one is gone: the tokens could not be checked
    /// (the note says so).
    Unchecked(String),
}

impl CheckpointCheck {
    /// The note to show, if the check could not be made.
    pub fn note(&self) -> Option<&str> {
        match self {
            CheckpointCheck::Verified(_) => None,
            CheckpointCheck::Unchecked(note) => Some(note),
        }
    }
}

/// Whether the tokens of the folder `dir` (its manifest `manifest`) still belong to their
/// checkpoint. With `given` (the checkpoint the caller means to use), its hash must be the
/// recorded one; without, the file at the recorded path must have it, and when that file is
/// gone the tokens are accepted unchecked, with a note. A changed checkpoint is an error saying
/// to run `velox encode` again.
pub fn check_checkpoint(
    dir: &Path,
    manifest: &TokenManifest,
    given: Option<&Path>,
) -> Result<CheckpointCheck> {
    let origin = &manifest.origin;
    let path = match given {
        Some(p) => p.to_path_buf(),
        None if !origin.checkpoint.exists() => {
            return Ok(CheckpointCheck::Unchecked(format!(
                "the checkpoint {} that {} was encoded with is gone: the tokens cannot be checked against it",
                origin.checkpoint.display(),
                dir.join(MANIFEST).display()
            )))
        }
        None => origin.checkpoint.clone(),
    };
    let hash = checkpoint_hash(&path)?;
    if hash != origin.checkpoint_hash {
        return Err(Error::Invalid(format!(
            "the tokens in {} were encoded with checkpoint {} (hash {}), but {} has hash {hash}: the encoder \
             changed, so run `velox encode --checkpoint {} --force` again",
            dir.display(),
            origin.checkpoint.display(),
            origin.checkpoint_hash,
            path.display(),
            path.display()
        )));
    }
    Ok(CheckpointCheck::Verified(path))
}

/// A token folder opened for reading: its manifest, checked, and its checkpoint checked.
#[derive(Clone, Debug)]
pub struct TokenFolder {
    pub dir: PathBuf,
    pub manifest: TokenManifest,
    pub checkpoint: CheckpointCheck,
}

impl TokenFolder {
    /// Reads the manifest of `dir` and checks the checkpoint ([`check_checkpoint`], with the
    /// caller's checkpoint `checkpoint` if any).
    pub fn open(dir: &Path, checkpoint: Option<&Path>) -> Result<TokenFolder> {
        let manifest = TokenManifest::read(dir)?;
        let checkpoint = check_checkpoint(dir, &manifest, checkpoint)?;
        Ok(TokenFolder { dir: dir.to_path_buf(), manifest, checkpoint })
    }

    /// The stored tokens of `scene`, which the manifest must list, read and checked
    /// ([`read_scene_file`]) and with the manifest's origin.
    pub fn read(&self, scene: &str) -> Result<SceneTokens> {
        if !self.manifest.scenes.iter().any(|s| s == scene) {
            return Err(Error::Invalid(format!(
                "{} lists no scene {scene:?}: run `velox encode` over its dataset again",
                self.dir.join(MANIFEST).display()
            )));
        }
        let path = scene_file(&self.dir, scene);
        let (origin, tokens) = read_scene_file(&path)?;
        let differences = origin.differences(&self.manifest.origin);
        if !differences.is_empty() {
            return Err(Error::Invalid(format!(
                "{}: encoded otherwise than {} says ({}): run `velox encode` again",
                path.display(),
                MANIFEST,
                differences.join("; ")
            )));
        }
        Ok(tokens)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use velox_engine::FileOp;

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("velox-tokens-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn origin(checkpoint: &Path, hash: &str) -> TokenOrigin {
        TokenOrigin {
            checkpoint: checkpoint.to_path_buf(),
            checkpoint_hash: hash.into(),
            config: AutoencoderConfig::tiny(),
            seed: 5,
            precision: Precision::F16,
            source: CloudSource::Points,
        }
    }

    /// Scene tokens of the tiny config's shape, values from `at`.
    fn tokens(scene: &str, at: f32) -> SceneTokens {
        let (k, d) = origin(Path::new("x"), "0").shape();
        let t = (0..k * d).map(|i| at + (i as f32 * 0.37).sin()).collect();
        let p = (0..k).flat_map(|i| [0.5, -0.25, i as f32 / k as f32, (i % 24) as f32 / 100.0]).collect();
        SceneTokens::new(scene, t, p, d).unwrap()
    }

    #[test]
    fn fnv1a_matches_the_published_vectors() {
        let hash = |s: &str| {
            let mut h = Fnv1a::new();
            h.update(s.as_bytes());
            hash_hex(h.finish())
        };
        assert_eq!(hash(""), "cbf29ce484222325");
        assert_eq!(hash("a"), "af63dc4c8601ec8c");
        assert_eq!(hash("foobar"), "85944171f73967e8");
        // In pieces as at once, and a file as its bytes.
        let mut h = Fnv1a::new();
        h.update(b"foo");
        h.update(b"bar");
        assert_eq!(hash_hex(h.finish()), "85944171f73967e8");
        let dir = temp_dir("fnv");
        std::fs::write(dir.join("f"), b"foobar").unwrap();
        assert_eq!(checkpoint_hash(&dir.join("f")).unwrap(), "85944171f73967e8");
        let e = checkpoint_hash(&dir.join("none")).unwrap_err();
        assert!(matches!(&e, Error::File { path, op: FileOp::Read, .. } if path.ends_with("none")), "{e}");
        assert!(check_hash("85944171F73967E8").is_err() && check_hash("8594417").is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_scene_file_round_trips_to_the_same_bytes_and_names_its_problems() {
        let dir = temp_dir("scene");
        let o = origin(&dir.join("ae.safetensors"), "0123456789abcdef");
        let t = tokens("scene_00003", 0.5);
        let path = write_scene_file(&dir, &o, &t).unwrap();
        assert_eq!(path, dir.join("scene_00003.safetensors"));
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(read_scene_file(&path).unwrap(), (o.clone(), t.clone()));
        write_scene_file(&dir, &o, &t).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), bytes, "the same tokens give the same bytes");
        // Renamed, the file no longer says its name.
        let moved = dir.join("scene_00004.safetensors");
        std::fs::rename(&path, &moved).unwrap();
        let e = read_scene_file(&moved).unwrap_err().to_string();
        assert!(
            e.contains("scene_00004.safetensors") && e.contains("belong in a file named scene_00003"),
            "{e}"
        );
        // Shapes other than the origin's, bad values and bad names are refused.
        let mut wide = o.clone();
        wide.config.encoder.token_dim += 1;
        assert!(write_scene_file(&dir, &wide, &t)
            .unwrap_err()
            .to_string()
            .contains("the origin's config makes"));
        let mut nan = t.tokens.clone();
        nan[9] = f32::NAN;
        let e = SceneTokens::new("s", nan, t.query_points.clone(), t.token_dim).unwrap_err().to_string();
        assert!(e.contains("token 1 channel 1 is NaN"), "{e}");
        let mut far = t.query_points.clone();
        far[4] = 1.5;
        let e = SceneTokens::new("s", t.tokens.clone(), far, t.token_dim).unwrap_err().to_string();
        assert!(e.contains("query point 1"), "{e}");
        let short = t.query_points[4..].to_vec();
        assert!(SceneTokens::new("s", t.tokens.clone(), short, t.token_dim).is_err());
        for name in ["", ".hidden", "a/b", "a\\b"] {
            assert!(SceneTokens::new(name, t.tokens.clone(), t.query_points.clone(), 8).is_err(), "{name:?}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn stats_merged_in_order_equal_the_stats_of_all_rows() {
        let (a, b) = (tokens("a", 3.0), tokens("b", -1.0));
        let d = a.token_dim;
        let mut merged = TokenStats::of(&a.tokens, d);
        merged.merge(&TokenStats::of(&b.tokens, d));
        let all = TokenStats::of(&[a.tokens.clone(), b.tokens.clone()].concat(), d);
        assert_eq!(merged.count(), all.count());
        for c in 0..d {
            assert!((merged.mean()[c] - all.mean()[c]).abs() <= 1e-14 * all.mean()[c].abs().max(1.0));
            assert!((merged.std()[c] - all.std()[c]).abs() <= 1e-13 * all.std()[c].max(1.0));
        }
        // The first channel by hand: means 3 + sin 0 = 3 and -1 (plus the same offsets).
        let col: Vec<f64> = [&a, &b].iter().flat_map(|t| t.tokens.chunks(d).map(|r| r[0] as f64)).collect();
        let mean = col.iter().sum::<f64>() / col.len() as f64;
        let var = col.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / col.len() as f64;
        assert!((merged.mean()[0] - mean).abs() < 1e-12 && (merged.std()[0] - var.sqrt()).abs() < 1e-12);
        let mut empty = TokenStats::default();
        empty.merge(&merged);
        assert_eq!(empty, merged);
        assert_eq!(TokenStats::of(&[1.0, 2.0], 0), TokenStats::default(), "no channels, no rows");
    }

    #[test]
    fn manifests_round_trip_and_bad_ones_are_named() {
        let dir = temp_dir("manifest");
        let o = origin(&dir.join("ae.safetensors"), "0123456789abcdef");
        let stats = TokenStats::of(&tokens("a", 0.0).tokens, 8);
        let m = TokenManifest::new(o, vec!["a".into(), "b".into()], &stats);
        m.write(&dir).unwrap();
        assert_eq!(TokenManifest::read(&dir).unwrap(), m);
        let bad = |edit: &dyn Fn(&mut serde_json::Value), want: &str| {
            let mut v = serde_json::to_value(&m).unwrap();
            edit(&mut v);
            std::fs::write(dir.join(MANIFEST), v.to_string()).unwrap();
            let e = TokenManifest::read(&dir).unwrap_err().to_string();
            assert!(e.contains("tokens.json") && e.contains(want), "{want}: {e}");
        };
        bad(&|v| v["scenes"] = serde_json::json!(["a", "a"]), "twice");
        bad(&|v| v["scenes"] = serde_json::json!([]), "no scenes");
        bad(&|v| v["scenes"] = serde_json::json!(["../x"]), "not a folder name");
        bad(&|v| v["origin"]["checkpoint_hash"] = "xyz".into(), "16 lowercase hex digits");
        bad(&|v| v["origin"]["precision"] = "f8".into(), "not f32 or f16");
        bad(&|v| v["tokens"] = 7.into(), "the config makes");
        bad(&|v| v["std"][2] = (-1.0).into(), "std of channel 2");
        bad(&|v| v["mean"] = serde_json::json!([0.0]), "mean has 1 channels");
        bad(&|v| v["origin"]["config"]["encoder"]["heads"] = 3.into(), "config");
        bad(&|v| v["extra"] = 1.into(), "unknown field");
        std::fs::remove_file(dir.join(MANIFEST)).unwrap();
        let e = TokenManifest::read(&dir).unwrap_err().to_string();
        assert!(e.contains("velox encode"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_changed_checkpoint_is_refused_and_a_gone_one_noted() {
        let dir = temp_dir("check");
        let ckpt = dir.join("ae.safetensors");
        std::fs::write(&ckpt, b"weights").unwrap();
        let hash = checkpoint_hash(&ckpt).unwrap();
        let m = TokenManifest::new(origin(&ckpt, &hash), vec!["a".into()], &TokenStats::of(&[0.0; 8], 8));
        assert_eq!(check_checkpoint(&dir, &m, None).unwrap(), CheckpointCheck::Verified(ckpt.clone()));
        // A copy elsewhere is the same checkpoint.
        let copy = dir.join("copy.safetensors");
        std::fs::copy(&ckpt, &copy).unwrap();
        assert_eq!(check_checkpoint(&dir, &m, Some(&copy)).unwrap(), CheckpointCheck::Verified(copy.clone()));
        // Changed at its path: refused, with or without naming it.
        std::fs::write(&ckpt, b"weights, trained further").unwrap();
        for given in [None, Some(ckpt.as_path())] {
            let e = check_checkpoint(&dir, &m, given).unwrap_err().to_string();
            assert!(e.contains("encoder changed") && e.contains("velox encode") && e.contains(&hash), "{e}");
        }
        // The copy named still matches, whatever the recorded path now holds.
        assert!(check_checkpoint(&dir, &m, Some(&copy)).is_ok());
        // Gone: accepted with a note when none is named, refused when another is named.
        std::fs::remove_file(&ckpt).unwrap();
        let check = check_checkpoint(&dir, &m, None).unwrap();
        assert!(check.note().is_some_and(|n| n.contains("is gone")), "{check:?}");
        std::fs::write(&copy, b"other weights").unwrap();
        assert!(check_checkpoint(&dir, &m, Some(&copy)).is_err());
        let e = check_checkpoint(&dir, &m, Some(&ckpt)).unwrap_err();
        assert!(matches!(e, Error::File { op: FileOp::Read, .. }), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
