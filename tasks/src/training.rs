//! Scenes as the autoencoder trains on them: the cloud, the supervision cameras in the
//! rasteriser's form, and the supervision images as f32 RGB in [0, 1]; and a dataset folder as
//! the trainer's [`SampleSource`] of them ([`SceneFolders`]). For the models that train on a
//! frozen encoder's stored tokens (`velox encode`), a dataset folder and its token folder as
//! a [`SampleSource`] of [`VoxelSample`]s ([`TokenScenes`]).

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use velox_engine::ops::raster::Camera;
use velox_engine::{Error, Gpu};
use velox_models::config::GeneratorConfig;
use velox_models::train::source::SampleSource;
use velox_models::velox::autoencoder::TrainScene;
use velox_models::velox::dinov2::{Dinov2, PATCH_VALUES};
use velox_models::velox::generator::{Condition, GenSample};
use velox_models::velox::tokens::{
    scene_file, CheckpointCheck, CloudSource, SceneTokens, TokenFolder, TokenManifest, MANIFEST,
};
use velox_models::velox::tracker::{Track, TrackSample};
use velox_models::velox::voxels::VoxelSample;

use crate::condition::read_condition_video;
use crate::encode::dataset_scenes;
use velox_data::format::{list_some_scenes, read_occupancy, read_scene, read_video_tracks, Scene};
use velox_data::{DataError, DataResult};

/// A scene read into host memory, ready to upload: what the trainer's background thread
/// hands over.
pub struct HostScene {
    pub dir: PathBuf,
    /// Rows of (x, y, z, r, g, b, tau).
    pub cloud: Vec<f32>,
    pub cameras: Vec<Camera>,
    /// Frame-major then view, RGB in [0, 1].
    pub images: Vec<Vec<f32>>,
    /// The images' background.
    pub background: [f32; 3],
}

impl HostScene {
    /// The training form of a scene read with its images (`read_scene(dir, true)`).
    pub fn new(scene: &Scene) -> DataResult<HostScene> {
        if scene.supervision.is_empty() {
            return Err(DataError::Invalid(format!(
                "{}: the scene was read without its images; training needs them",
                scene.dir.display()
            )));
        }
        Ok(HostScene {
            dir: scene.dir.clone(),
            cloud: scene.points.iter().flatten().copied().collect(),
            cameras: scene.cameras.supervision.clone(),
            images: scene
                .supervision
                .iter()
                .map(|img| img.iter().map(|&b| b as f32 / 255.0).collect())
                .collect(),
            background: scene.meta.background,
        })
    }

    /// Checks the scene and uploads it; the error names its folder.
    pub fn upload(self, gpu: &Gpu) -> DataResult<TrainScene> {
        let dir = self.dir;
        TrainScene::new(gpu, self.cloud, self.cameras, self.images)
            .map(|s| s.with_background(self.background))
            .map_err(|e| DataError::Invalid(format!("{}: {e}", dir.display())))
    }
}

/// Uploads a scene read with its images (`read_scene(dir, true)`) for training.
pub fn train_scene(gpu: &Gpu, scene: &Scene) -> DataResult<TrainScene> {
    HostScene::new(scene)?.upload(gpu)
}

/// The scenes of a dataset folder (as `velox data` writes them), in name order, as samples
/// for the trainer and the evaluation: read with their images on the reading thread, uploaded
/// to `gpu` when prepared.
pub struct SceneFolders {
    gpu: Gpu,
    dirs: Vec<PathBuf>,
}

impl SceneFolders {
    /// The scenes under `root`; none is an error that says how to make some.
    pub fn open(gpu: &Gpu, root: &Path) -> DataResult<SceneFolders> {
        Ok(SceneFolders { gpu: gpu.clone(), dirs: list_some_scenes(root)? })
    }

    /// Keeps the first `n` scenes.
    pub fn truncate(&mut self, n: usize) {
        self.dirs.truncate(n);
    }

    /// The scene folders, in name order.
    pub fn dirs(&self) -> &[PathBuf] {
        &self.dirs
    }
}

impl SampleSource for SceneFolders {
    type Raw = HostScene;
    type Sample = TrainScene;

    fn len(&self) -> usize {
        self.dirs.len()
    }

    fn name(&self, index: usize) -> String {
        self.dirs[index].file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
    }

    fn location(&self, index: usize) -> String {
        self.dirs[index].display().to_string()
    }

    fn read(&self, index: usize) -> velox_engine::Result<HostScene> {
        Ok(HostScene::new(&read_scene(&self.dirs[index], true)?)?)
    }

    fn prepare(&self, raw: HostScene) -> velox_engine::Result<TrainScene> {
        Ok(raw.upload(&self.gpu)?)
    }
}

/// A scene's stored tokens and its occupancy, read into host memory.
pub struct HostTokenScene {
    pub tokens: SceneTokens,
    /// 4096 words per frame, every frame (`occupancy.bin`).
    pub occupancy: Vec<u64>,
}

/// The scenes of a dataset folder with their tokens stored by `velox encode`, in the dataset's
/// name order, as samples for the models that train on the frozen encoder's tokens: each scene's
/// tokens (checked against the folder's manifest) and its occupancy (`occupancy.bin`, without
/// the points or the images), uploaded as a [`VoxelSample`] when prepared. The manifest's mean
/// and standard deviation are at hand for the models that normalise tokens.
pub struct TokenScenes {
    gpu: Gpu,
    dirs: Vec<PathBuf>,
    names: Vec<String>,
    folder: TokenFolder,
}

/// At most this many names in an error that lists scenes.
const NAMES_SHOWN: usize = 5;

fn some_names(names: &[&String]) -> String {
    let shown: Vec<&str> = names.iter().take(NAMES_SHOWN).map(|n| n.as_str()).collect();
    let more = names.len().saturating_sub(NAMES_SHOWN);
    if more > 0 {
        format!("{} and {more} more", shown.join(", "))
    } else {
        shown.join(", ")
    }
}

impl TokenScenes {
    /// The scenes under `data` and their tokens in the folder `tokens` (`None`: `DATA/tokens`,
    /// where `velox encode` writes them). The token folder must hold every scene of the dataset
    /// and no other, each scene's file present; its checkpoint is checked as
    /// `velox_models::velox::tokens::check_checkpoint` does, against `checkpoint` (the encoder
    /// the caller uses) when given: a changed checkpoint is an error saying to run `velox
    /// encode` again, and one that is gone is accepted when none is given, with a note
    /// ([`TokenScenes::checkpoint`]).
    pub fn open(
        gpu: &Gpu,
        data: &Path,
        tokens: Option<&Path>,
        checkpoint: Option<&Path>,
    ) -> DataResult<TokenScenes> {
        TokenScenes::open_source(gpu, data, tokens, checkpoint, CloudSource::Points)
    }

    /// As [`TokenScenes::open`], for tokens of the scenes' `source` cloud (the folder's
    /// default is that source's, `DATA/tokens-video` for the videos); tokens of the other
    /// cloud are refused.
    pub fn open_source(
        gpu: &Gpu,
        data: &Path,
        tokens: Option<&Path>,
        checkpoint: Option<&Path>,
        source: CloudSource,
    ) -> DataResult<TokenScenes> {
        let (dirs, names) = dataset_scenes(data)?;
        let token_dir = tokens.map_or_else(|| data.join(source.default_dir()), Path::to_path_buf);
        let encode = match source {
            CloudSource::Points => {
                format!("`velox encode --data {}`, or velox.encode_dataset", data.display())
            }
            CloudSource::Video => format!(
                "`velox encode --source video --data {}`, or velox.encode_dataset with source=\"video\"",
                data.display()
            ),
        };
        let folder = TokenFolder::open(&token_dir, checkpoint)
            .map_err(|e| DataError::Invalid(format!("{e} (tokens are made by {encode})")))?;
        let manifest = token_dir.join(MANIFEST);
        let stored = folder.manifest.origin.source;
        if stored != source {
            return Err(DataError::Invalid(format!(
                "{} holds tokens of the scenes' {} clouds; this model reads tokens of their {}: run `{encode}`",
                manifest.display(),
                stored.name(),
                source.name()
            )));
        }
        let listed: std::collections::BTreeSet<&String> = folder.manifest.scenes.iter().collect();
        let present: std::collections::BTreeSet<&String> = names.iter().collect();
        let missing: Vec<&String> = present.difference(&listed).copied().collect();
        if !missing.is_empty() {
            return Err(DataError::Invalid(format!(
                "{} lacks {} scene(s) of {}: {}; run `{encode}` to encode them",
                manifest.display(),
                missing.len(),
                data.display(),
                some_names(&missing),
            )));
        }
        let extra: Vec<&String> = listed.difference(&present).copied().collect();
        if !extra.is_empty() {
            return Err(DataError::Invalid(format!(
                "{} lists {} scene(s) that {} lacks: {} (the tokens of another dataset, or scenes since \
                 removed?); run `{encode}` again",
                manifest.display(),
                extra.len(),
                data.display(),
                some_names(&extra),
            )));
        }
        if let Some(name) = names.iter().find(|n| !scene_file(&token_dir, n).is_file()) {
            return Err(DataError::Invalid(format!(
                "{} lists scene {name}, but {} is missing; run `{encode}` again",
                manifest.display(),
                scene_file(&token_dir, name).display(),
            )));
        }
        Ok(TokenScenes { gpu: gpu.clone(), dirs, names, folder })
    }

    /// Fails unless a model downstream of the encoder (`what`, trained on the tokens of the
    /// autoencoder of hash `trained_on` if it recorded one, reading tokens `token_dim` wide)
    /// fits these tokens.
    pub fn check_model(&self, what: &str, trained_on: Option<&str>, token_dim: usize) -> DataResult<()> {
        let (from, stored) = (&self.folder.manifest.origin.checkpoint_hash, self.folder.manifest.token_dim);
        let dir = self.folder.dir.display();
        if let Some(hash) = trained_on.filter(|h| h != from) {
            return Err(DataError::Invalid(format!(
                "the {what} trained on tokens of autoencoder checkpoint {hash}, {dir} holds tokens of {from}"
            )));
        }
        if token_dim != stored {
            return Err(DataError::Invalid(format!(
                "the {what} reads tokens {token_dim} wide and {dir} holds tokens {stored} wide"
            )));
        }
        Ok(())
    }

    /// The token folder's manifest: the encoder's origin, k and token_dim, the statistics.
    pub fn manifest(&self) -> &TokenManifest {
        &self.folder.manifest
    }

    /// How the checkpoint was checked (a note when it could not be).
    pub fn checkpoint(&self) -> &CheckpointCheck {
        &self.folder.checkpoint
    }

    /// The token folder.
    pub fn token_dir(&self) -> &Path {
        &self.folder.dir
    }

    /// The scene folders, in name order.
    pub fn dirs(&self) -> &[PathBuf] {
        &self.dirs
    }
}

impl SampleSource for TokenScenes {
    type Raw = HostTokenScene;
    type Sample = VoxelSample;

    fn len(&self) -> usize {
        self.dirs.len()
    }

    fn name(&self, index: usize) -> String {
        self.names[index].clone()
    }

    fn location(&self, index: usize) -> String {
        self.dirs[index].display().to_string()
    }

    fn read(&self, index: usize) -> velox_engine::Result<HostTokenScene> {
        let tokens = self.folder.read(&self.names[index])?;
        let occupancy = read_occupancy(&self.dirs[index])?;
        Ok(HostTokenScene { tokens, occupancy })
    }

    fn prepare(&self, raw: HostTokenScene) -> velox_engine::Result<VoxelSample> {
        VoxelSample::new(raw.tokens.upload(&self.gpu)?, raw.occupancy)
    }
}

/// A scene's stored tokens (of its video's cloud) and its video tracks, read into host memory.
pub struct HostTrackScene {
    pub tokens: SceneTokens,
    pub tracks: Vec<Track>,
    /// Each track's colour on the video's first frame (its query's pixel).
    pub colours: Vec<[f32; 3]>,
    /// Whether the video camera sees each track at each frame (the evaluation's truth; the
    /// training does not use it).
    pub visible: Vec<[bool; velox_models::velox::autoencoder::FRAMES]>,
}

/// The scenes of a dataset with the tokens of their RGBD videos (`velox encode --source
/// video`), as the tracker's samples: each scene's tokens and its video tracks (the queries
/// and their true positions, `video_tracks.bin`).
pub struct TrackScenes(pub TokenScenes);

impl TrackScenes {
    /// As [`TokenScenes::open_source`] for the videos' tokens.
    pub fn open(
        gpu: &Gpu,
        data: &Path,
        tokens: Option<&Path>,
        checkpoint: Option<&Path>,
    ) -> DataResult<TrackScenes> {
        Ok(TrackScenes(TokenScenes::open_source(gpu, data, tokens, checkpoint, CloudSource::Video)?))
    }

    /// Scene `index` as a sample, with whether the video camera sees each track at each
    /// frame: what the evaluation needs, read once.
    pub fn load_with_visibility(
        &self,
        index: usize,
    ) -> velox_engine::Result<(TrackSample, Vec<[bool; velox_models::velox::autoencoder::FRAMES]>)> {
        let mut raw = self.read(index)?;
        let visible = std::mem::take(&mut raw.visible);
        Ok((self.prepare(raw)?, visible))
    }
}

impl SampleSource for TrackScenes {
    type Raw = HostTrackScene;
    type Sample = TrackSample;

    fn len(&self) -> usize {
        self.0.dirs.len()
    }

    fn name(&self, index: usize) -> String {
        self.0.names[index].clone()
    }

    fn location(&self, index: usize) -> String {
        self.0.dirs[index].display().to_string()
    }

    fn read(&self, index: usize) -> velox_engine::Result<HostTrackScene> {
        let tokens = self.0.folder.read(&self.0.names[index])?;
        let (tracks, visible) = read_video_tracks(&self.0.dirs[index])?;
        if tracks.is_empty() {
            return Err(DataError::Invalid(format!(
                "{}: the scene has no video tracks (made with 0 tracks, or before the tracking task): \
                 make the data again with tracks",
                self.0.dirs[index].display()
            ))
            .into());
        }
        let dir = &self.0.dirs[index];
        let camera = velox_data::rgbd::scene_video_camera(dir)?;
        let frame = velox_data::rgbd::read_colour_frame(&dir.join("video"), &camera, 0)?;
        let queries: Vec<[f32; 3]> = tracks.iter().map(|t| t[0]).collect();
        let colours = velox_data::rgbd::colours_at(&frame, &camera, &queries);
        Ok(HostTrackScene { tokens, tracks, colours, visible })
    }

    fn prepare(&self, raw: HostTrackScene) -> velox_engine::Result<TrackSample> {
        let points =
            velox_engine::Tensor::from_slice(&self.0.gpu, &[raw.tokens.k(), 4], &raw.tokens.query_points)?;
        TrackSample::new(raw.tokens.upload(&self.0.gpu)?, points, raw.tracks, raw.colours)
    }
}

/// A scene's tokens, normalised by the dataset's statistics, and its condition frames
/// (`[frames, 3, size, size]`, see [`crate::condition`]), read into host memory.
pub struct HostGenScene {
    pub index: usize,
    pub tokens: Vec<f32>,
    pub pixels: Vec<f32>,
}

/// The scenes of a dataset with their stored tokens (`velox encode`) as the generator's
/// samples: each scene's tokens normalised by the statistics the generator records, and the
/// condition of its conditioning video (its RGB patches and, with DINOv2, their features,
/// computed once per scene and kept on the device).
pub struct GenScenes {
    pub tokens: TokenScenes,
    cfg: GeneratorConfig,
    dino: Option<Dinov2>,
    dino_cache: Mutex<Vec<Option<velox_engine::Tensor>>>,
}

impl GenScenes {
    /// Fails unless the generator `cfg` fits the stored tokens (their count, width and
    /// statistics) and `dino` (features as wide as it reads, or none when it reads none).
    pub fn new(tokens: TokenScenes, cfg: &GeneratorConfig, dino: Option<Dinov2>) -> DataResult<GenScenes> {
        let m = tokens.manifest();
        if (cfg.tokens, cfg.token_dim) != (m.tokens, m.token_dim) {
            return Err(DataError::Invalid(format!(
                "the generator makes {} tokens {} wide; {} holds {} tokens {} wide",
                cfg.tokens,
                cfg.token_dim,
                tokens.token_dir().display(),
                m.tokens,
                m.token_dim
            )));
        }
        if cfg.token_mean.len() != cfg.token_dim {
            return Err(DataError::Invalid("the generator has no token statistics to normalise by".into()));
        }
        let width = dino.as_ref().map_or(0, |d| d.config.width);
        if width != cfg.dino_width {
            return Err(DataError::Engine(Error::setting(
                "dinov2",
                match cfg.dino_width {
                    0 => "the generator reads no DINOv2 features, but DINOv2 weights were given ({dinov2})"
                        .into(),
                    w => format!(
                        "the generator reads {w}-wide DINOv2 features; give its DINOv2 weights ({{dinov2}})"
                    ),
                },
            )));
        }
        let n = tokens.dirs().len();
        Ok(GenScenes { tokens, cfg: cfg.clone(), dino, dino_cache: Mutex::new(vec![None; n]) })
    }

    /// The condition of frames `pixels` (`[frames, 3, size, size]`) for the generator `cfg`:
    /// the RGB patches, and DINOv2's patch features of them when it reads them.
    pub fn condition(
        gpu: &Gpu,
        cfg: &GeneratorConfig,
        dino: Option<&Dinov2>,
        pixels: &[f32],
    ) -> velox_engine::Result<Condition> {
        let (frames, size) = (cfg.task.frames(), cfg.image_size);
        let patches = Dinov2::image_patches(pixels, frames, size, size)?;
        let patches =
            velox_engine::Tensor::from_slice(gpu, &[patches.len() / PATCH_VALUES, PATCH_VALUES], &patches)?;
        let dino = dino
            .map(|d| d.patch_features(gpu, pixels, frames, size, size, velox_engine::Precision::F32))
            .transpose()?;
        Ok(Condition { patches, dino })
    }
}

impl SampleSource for GenScenes {
    type Raw = HostGenScene;
    type Sample = GenSample;

    fn len(&self) -> usize {
        self.tokens.dirs.len()
    }

    fn name(&self, index: usize) -> String {
        self.tokens.names[index].clone()
    }

    fn location(&self, index: usize) -> String {
        self.tokens.dirs[index].display().to_string()
    }

    fn read(&self, index: usize) -> velox_engine::Result<HostGenScene> {
        let raw = self.tokens.folder.read(&self.tokens.names[index])?;
        let tokens = self.cfg.normalise(&raw.tokens);
        let video = self.tokens.dirs[index].join("video");
        let pixels = read_condition_video(&video, self.cfg.task.frames(), self.cfg.image_size)?;
        Ok(HostGenScene { index, tokens, pixels })
    }

    fn prepare(&self, raw: HostGenScene) -> velox_engine::Result<GenSample> {
        let gpu = &self.tokens.gpu;
        let (k, d) = (self.cfg.tokens, self.cfg.token_dim);
        let tokens = velox_engine::Tensor::from_slice(gpu, &[k, d], &raw.tokens)?;
        // DINOv2 runs once per scene; its features stay on the device for the later steps.
        let cached = self.dino_cache.lock().unwrap()[raw.index].clone();
        let fresh = cached.is_none().then_some(self.dino.as_ref()).flatten();
        let mut condition = GenScenes::condition(gpu, &self.cfg, fresh, &raw.pixels)?;
        match (cached, &condition.dino) {
            (Some(features), _) => condition.dino = Some(features),
            (None, Some(features)) => self.dino_cache.lock().unwrap()[raw.index] = Some(features.clone()),
            (None, None) => {}
        }
        Ok(GenSample { tokens, condition })
    }
}
