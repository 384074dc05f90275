//! Encoding a dataset once (`velox encode`): a trained autoencoder's encoder over every scene's
//! whole cloud, each scene's tokens and query points stored in a token folder with the
//! dataset's token statistics (`velox_models::velox::tokens` gives the layout), so the models
//! downstream of the encoder train on stored tokens with the encoder frozen
//! ([`crate::training::TokenScenes`]).
//!
//! Scene by scene, in name order: the cloud (`points.ply`, checked; or with
//! [`CloudSource::Video`] the scene's RGBD video back-projected, `velox_data::rgbd`) is encoded with the
//! queries drawn from the seed (`Autoencoder::encode_with_queries`, the encoder of `velox
//! decode` and `velox eval`); the tokens, bit for bit, and the cloud's rows at the query
//! indices (x, y, z, tau) go to `SCENE.safetensors`. The manifest, written last, lists every
//! scene and holds the per-channel statistics over all of them.
//!
//! Over a folder that holds tokens already:
//! - of the same checkpoint (its hash), seed and precision: a scene whose file is there is
//!   kept (read and checked, for the statistics) and only the others are encoded, so an
//!   interrupted run resumes where it stopped; `force` encodes every scene again;
//! - of another checkpoint, seed or precision (the manifest's or any scene file's origin): it
//!   is refused, saying what differs, unless `force`, which removes the old manifest first
//!   (a run stopped half way leaves no manifest to trust) and encodes every scene;
//! - a scene file that cannot be read is refused (naming it) unless `force`.
//!
//! Files of scenes the dataset no longer holds are left in the folder; the manifest does not
//! list them, so nothing reads them.

use std::path::{Path, PathBuf};
use std::time::Instant;

use velox_engine::{Error, Gpu, Precision};
use velox_io::cloud::{self, CHANNELS};
use velox_models::velox::autoencoder::Autoencoder;
use velox_models::velox::tokens::{
    check_scene_name, checkpoint_hash, read_scene_file, scene_file, write_scene_file, CloudSource,
    SceneTokens, TokenManifest, TokenOrigin, TokenStats, MANIFEST,
};
use velox_models::Model;

use velox_data::format::{list_some_scenes, read_ply};
use velox_data::{DataError, DataResult};

/// What to encode, with what, and where to.
#[derive(Clone, Debug)]
pub struct EncodeOptions {
    /// The autoencoder checkpoint whose encoder encodes.
    pub checkpoint: PathBuf,
    /// The dataset folder (scenes as `velox data` writes them).
    pub data: PathBuf,
    /// The token folder; `None`: `DATA/tokens`, beside the scenes.
    pub out: Option<PathBuf>,
    /// Seed of the encoder's queries.
    pub seed: u64,
    /// The precision the encoder runs in.
    pub precision: Precision,
    /// Encode every scene again, and replace tokens of another checkpoint, seed or precision.
    pub force: bool,
    /// The cloud to encode: `points.ply`, or the RGBD video back-projected (at most
    /// `video_points` of its pixels, drawn with `seed`).
    pub source: CloudSource,
    pub video_points: usize,
}

impl EncodeOptions {
    /// The token folder the options name.
    pub fn out_dir(&self) -> PathBuf {
        self.out.clone().unwrap_or_else(|| self.data.join(self.source.default_dir()))
    }
}

/// What an encoding tells as it goes; the library prints nothing.
pub trait EncodeObserver {
    /// The work is known: `to_encode` scenes to encode, `kept` found stored already.
    fn start(&mut self, _to_encode: usize, _kept: usize) {}
    /// Scene `name` is encoded and stored.
    fn encoded(&mut self, _name: &str) {}
}

/// Observes nothing.
impl EncodeObserver for () {}

/// What an encoding did.
#[derive(Clone, Debug)]
pub struct EncodeReport {
    /// The token folder.
    pub dir: PathBuf,
    /// The manifest written.
    pub manifest: TokenManifest,
    /// Scenes encoded by this run, and scenes whose stored tokens were kept.
    pub encoded: Vec<String>,
    pub kept: Vec<String>,
    /// With `force` over tokens of another origin: what differed.
    pub replaced: Option<String>,
    /// Points encoded, and the seconds the encoder took (reading and writing included).
    pub points: usize,
    pub encode_seconds: f64,
}

/// A scene folder's name, checked as the token store names files.
fn scene_name(dir: &Path) -> DataResult<String> {
    let name = dir.file_name().and_then(|n| n.to_str()).ok_or_else(|| {
        DataError::Invalid(format!(
            "{}: a scene folder's name must be UTF-8 to name its tokens",
            dir.display()
        ))
    })?;
    check_scene_name(name).map_err(|why| DataError::Invalid(format!("{}: {why}", dir.display())))?;
    Ok(name.to_string())
}

/// The dataset's scene folders and their names, in name order; none is an error.
pub(crate) fn dataset_scenes(data: &Path) -> DataResult<(Vec<PathBuf>, Vec<String>)> {
    let dirs = list_some_scenes(data)?;
    let names = dirs.iter().map(|d| scene_name(d)).collect::<DataResult<Vec<_>>>()?;
    Ok((dirs, names))
}

/// Encodes every scene of `options.data` into the token folder (see the module docs).
pub fn encode_dataset(
    gpu: &Gpu,
    options: &EncodeOptions,
    observer: &mut dyn EncodeObserver,
) -> DataResult<EncodeReport> {
    let (dirs, names) = dataset_scenes(&options.data)?;
    let out = options.out_dir();
    let checkpoint = std::fs::canonicalize(&options.checkpoint).map_err(|e| {
        DataError::Io(format!("cannot read checkpoint {}: {e}", options.checkpoint.display()))
    })?;
    let hash = checkpoint_hash(&checkpoint)?;
    let mut ae = Autoencoder::load(gpu, &checkpoint)?;
    if checkpoint_hash(&checkpoint)? != hash {
        return Err(DataError::Invalid(format!(
            "checkpoint {} changed while it was read (a training run writing it?): run again",
            checkpoint.display()
        )));
    }
    ae.set_precision(options.precision)?;
    let origin = TokenOrigin {
        checkpoint,
        checkpoint_hash: hash,
        config: ae.cfg.clone(),
        seed: options.seed,
        precision: options.precision,
        source: options.source,
    };
    std::fs::create_dir_all(&out)
        .map_err(|e| DataError::Io(format!("cannot create {}: {e}", out.display())))?;

    let replaced = check_previous(&out, &origin, options.force)?;
    let (k, d) = origin.shape();
    let mut stats: Vec<Option<TokenStats>> = vec![None; names.len()];
    if !options.force {
        for (name, stat) in names.iter().zip(&mut stats) {
            let path = scene_file(&out, name);
            if !path.exists() {
                continue;
            }
            let (stored, tokens) = read_scene_file(&path).map_err(|e| {
                DataError::Engine(Error::setting(
                    "force",
                    format!("{e}; remove it to encode the scene again, or ask for {{force}}"),
                ))
            })?;
            let differences = stored.differences(&origin);
            if !differences.is_empty() {
                return Err(DataError::Engine(Error::setting(
                    "force",
                    format!(
                        "{} holds tokens encoded otherwise ({}): ask for {{force}} to replace them, or \
                         choose another {{out}}",
                        path.display(),
                        differences.join("; ")
                    ),
                )));
            }
            *stat = Some(TokenStats::of(&tokens.tokens, d));
        }
    }
    let kept: Vec<String> =
        names.iter().zip(&stats).filter(|(_, s)| s.is_some()).map(|(n, _)| n.clone()).collect();
    observer.start(names.len() - kept.len(), kept.len());

    let start = Instant::now();
    let (mut encoded, mut points) = (Vec::new(), 0);
    for ((dir, name), stat) in dirs.iter().zip(&names).zip(&mut stats) {
        if stat.is_some() {
            continue;
        }
        let (cloud, what) = match options.source {
            CloudSource::Points => (read_ply(&dir.join("points.ply"))?, dir.join("points.ply")),
            CloudSource::Video => {
                let video = velox_data::rgbd::read_scene_video(dir)?;
                (velox_data::rgbd::rgbd_cloud(&video, options.video_points, options.seed)?, dir.join("video"))
            }
        };
        let cloud: Vec<f32> = cloud.into_iter().flatten().collect();
        let n = cloud.len() / CHANNELS;
        if n < k {
            return Err(DataError::Invalid(format!(
                "{}: {n} points, and the encoder of {} needs at least {k}",
                what.display(),
                origin.checkpoint.display()
            )));
        }
        let (tokens, queries) = ae.encode_with_queries(&cloud::upload(gpu, &cloud)?, origin.seed)?;
        let query_points = cloud::query_points(&cloud, &queries.read::<u32>()?);
        let tokens = SceneTokens::new(name, tokens.read()?, query_points, d)
            .map_err(|e| DataError::Invalid(format!("{}: {e}", dir.display())))?;
        write_scene_file(&out, &origin, &tokens)?;
        *stat = Some(TokenStats::of(&tokens.tokens, d));
        points += n;
        encoded.push(name.clone());
        observer.encoded(name);
    }
    let encode_seconds = start.elapsed().as_secs_f64();

    let mut all = TokenStats::default();
    for s in stats.iter().flatten() {
        all.merge(s);
    }
    let manifest = TokenManifest::new(origin, names, &all);
    manifest.write(&out)?;
    Ok(EncodeReport { dir: out, manifest, encoded, kept, replaced, points, encode_seconds })
}

/// Checks the folder's manifest, if any, against `origin`: tokens of another origin are
/// refused unless `force`, which removes the manifest and returns what differed.
fn check_previous(out: &Path, origin: &TokenOrigin, force: bool) -> DataResult<Option<String>> {
    let path = out.join(MANIFEST);
    if !path.exists() {
        return Ok(None);
    }
    let differs = match TokenManifest::read(out) {
        Ok(m) => {
            let differences = m.origin.differences(origin);
            if differences.is_empty() {
                return Ok(None);
            }
            format!("tokens of {}", differences.join("; "))
        }
        Err(e) => format!("an unreadable manifest ({e})"),
    };
    if !force {
        return Err(DataError::Engine(Error::setting(
            "force",
            format!(
                "{} holds {differs}: ask for {{force}} to replace them, or choose another {{out}}",
                out.display()
            ),
        )));
    }
    std::fs::remove_file(&path)
        .map_err(|e| DataError::Io(format!("cannot remove {}: {e}", path.display())))?;
    Ok(Some(differs))
}
