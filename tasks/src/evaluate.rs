//! The evaluations of the models downstream of the encoder, scene by scene, on a dataset's
//! stored tokens: the voxel decoder, the tracker, and the generator (as images, and as cloth
//! that falls). Each reads the scenes, runs the model and measures it with the metrics of
//! `velox_models::eval`; an observer hears of each scene as it goes and is handed what a
//! command may draw. The library writes no files.
//! (The autoencoder's evaluation is `velox_models::eval::recon::evaluate`.)

use velox_data::cloth::ClothRecord;
use velox_data::rgbd::RgbdVideo;
use velox_engine::{Error, Gpu, Result, Tensor};
use velox_models::eval::cloth::{centre_of_mass, heights, ClothScene};
use velox_models::eval::generation::{FrameRenders, GenerationScene, GenerationViews};
use velox_models::eval::tracking::{Scaling, TrackingReport, TrackingScene};
use velox_models::eval::voxels::{SceneVoxels, VoxelMetrics};
use velox_models::train::source::SampleSource;
use velox_models::velox::autoencoder::FRAMES;
use velox_models::velox::decode::{Decoding, Sampling, VoxelSource};
use velox_models::velox::generator::GenerateSpec;
use velox_models::velox::tracker::{Track, Tracker};
use velox_models::velox::voxels::VoxelDecoder;

use crate::generate::GeneratorModels;
use crate::{TokenScenes, TrackScenes};

/// The tracker on every scene: its metrics, their mean, and the scenes left out.
pub struct TrackingEvaluation {
    pub scenes: Vec<TrackingReport>,
    pub mean: TrackingReport,
    /// Scenes whose video shows none of their tracks: the benchmark's metrics are 0 / 0 there
    /// (its mean turns NaN), so they are left out of the means, by name.
    pub left_out: Vec<String>,
}

/// What the tracker's evaluation tells as it goes.
pub trait TrackingObserver {
    /// Scene `name` starts.
    fn scene(&mut self, _name: &str) {}
    /// Scene number `index` (counting those left out) is measured: its video, the truth and the
    /// tracker's tracks, to draw.
    fn measured(
        &mut self,
        _index: usize,
        _name: &str,
        _video: &RgbdVideo,
        _scene: &TrackingScene,
        _predicted: &[Track],
    ) -> Result<()> {
        Ok(())
    }
    /// A scene is done (measured or left out).
    fn done(&mut self) {}
}

/// The tracker's TAPVid-3D metrics on the first `count` scenes, predictions rescaled by
/// `scaling` (see `velox_models::eval::tracking`). Fails where no scene's video shows any of
/// its tracks.
pub fn tracking(
    tracker: &Tracker,
    scenes: &TrackScenes,
    count: usize,
    scaling: Scaling,
    observer: &mut dyn TrackingObserver,
) -> Result<TrackingEvaluation> {
    let (mut reports, mut left_out) = (Vec::with_capacity(count), Vec::new());
    for i in 0..count.min(scenes.len()) {
        let name = scenes.name(i);
        observer.scene(&name);
        let dir = &scenes.0.dirs()[i];
        let (sample, visible) = scenes.load_with_visibility(i)?;
        let video = velox_data::rgbd::read_scene_video(dir)?;
        let scene = TrackingScene {
            truth: &sample.tracks,
            colours: &sample.colours,
            visible: &visible,
            camera: &video.camera,
            depth: &video.depth,
        };
        if !scene.shows_any() {
            left_out.push(name);
            observer.done();
            continue;
        }
        let (report, predicted) = velox_models::eval::tracking::evaluate_scene(
            tracker,
            &name,
            &sample.tokens,
            &sample.token_points,
            &scene,
            scaling,
        )?;
        observer.measured(i, &name, &video, &scene, &predicted)?;
        reports.push(report);
        observer.done();
    }
    if reports.is_empty() {
        return Err(Error::Invalid("no scene's video shows any of its tracks: nothing to measure".into()));
    }
    Ok(TrackingEvaluation { mean: TrackingReport::mean(&reports), scenes: reports, left_out })
}

/// The voxel decoder on every scene: per-scene metrics and their mean.
pub struct VoxelEvaluation {
    pub scenes: Vec<SceneVoxels>,
    pub mean: VoxelMetrics,
}

/// What the voxel decoder's evaluation tells as it goes.
pub trait VoxelObserver {
    /// Scene `name` starts.
    fn scene(&mut self, _name: &str) {}
    /// A scene is measured: its frames' predictions and its true occupancy (every frame's
    /// words one after another), to draw.
    fn measured(&mut self, _scene: &SceneVoxels, _occupancy: &[u64]) -> Result<()> {
        Ok(())
    }
}

/// The voxel decoder's occupancy metrics on frames `0, frame_step, ...` of the first `count`
/// scenes (see `velox_models::eval::voxels`).
pub fn voxels(
    decoder: &VoxelDecoder,
    scenes: &TokenScenes,
    count: usize,
    frame_step: usize,
    observer: &mut dyn VoxelObserver,
) -> Result<VoxelEvaluation> {
    let mut reports = Vec::with_capacity(count);
    for i in 0..count.min(scenes.len()) {
        let name = scenes.name(i);
        observer.scene(&name);
        let sample = scenes.load(i)?;
        let r = velox_models::eval::voxels::evaluate_scene(
            decoder,
            &name,
            &sample.tokens,
            &sample.occupancy,
            frame_step,
        )?;
        observer.measured(&r, &sample.occupancy)?;
        reports.push(r);
    }
    let mean = VoxelMetrics::mean(&reports.iter().map(|r| r.mean).collect::<Vec<_>>());
    Ok(VoxelEvaluation { scenes: reports, mean })
}

/// Scene `i`'s generated tokens (from its conditioning video, as the generator reads it) and
/// the encoder's stored tokens of it, both on the device.
pub fn token_pair(
    gpu: &Gpu,
    models: &GeneratorModels,
    scenes: &TokenScenes,
    i: usize,
    spec: &GenerateSpec,
) -> Result<(Tensor, Tensor)> {
    let cfg = &models.generator.cfg;
    let video = scenes.dirs()[i].join("video");
    let pixels = crate::condition::read_condition_video(&video, cfg.task.frames(), cfg.image_size)?;
    let made = models.generate(gpu, &pixels, spec, &mut |_| {})?;
    Ok((made, scenes.read(i)?.tokens.upload(gpu)?))
}

/// How the generator's evaluation decodes and renders.
pub struct GenerationOptions<'a> {
    pub spec: GenerateSpec,
    /// Where the Gaussian decoder's voxels come from, for both token sets.
    pub source: VoxelSource,
    /// The voxel decoder, for [`VoxelSource::Predicted`].
    pub voxel_decoder: Option<&'a VoxelDecoder>,
    /// The surface sampler, for [`VoxelSource::Surface`].
    pub sampling: Sampling,
    /// The frames measured.
    pub frames: Vec<usize>,
    /// Novel views: the first N supervision cameras of each scene.
    pub views: usize,
    /// The frames whose renders the observer is handed.
    pub kept: Vec<usize>,
}

/// What the generator's evaluation tells as it goes.
pub trait GenerationObserver {
    /// Scene `name` starts.
    fn scene(&mut self, _name: &str) {}
    /// The renders of a kept frame of scene `name`: per view (the input view first) truth,
    /// generated and encoded.
    fn renders(&mut self, _name: &str, _views: &GenerationViews, _frame: FrameRenders) -> Result<()> {
        Ok(())
    }
    /// Scene `name` is done.
    fn done(&mut self, _name: &str, _views: &GenerationViews) -> Result<()> {
        Ok(())
    }
}

/// The generator against the encoder on the first `count` scenes: the Gaussians of both token
/// sets rendered from the input view and novel views, against the scene's images (see
/// `velox_models::eval::generation`).
pub fn generation(
    gpu: &Gpu,
    models: &GeneratorModels,
    scenes: &TokenScenes,
    count: usize,
    options: &GenerationOptions,
    observer: &mut dyn GenerationObserver,
) -> Result<Vec<GenerationScene>> {
    let mut results = Vec::with_capacity(count);
    for i in 0..count.min(scenes.len()) {
        let dir = &scenes.dirs()[i];
        let name = scenes.name(i);
        observer.scene(&name);
        let scene = velox_data::read_scene(dir, true)?;
        let input = scene
            .cameras
            .video
            .ok_or_else(|| Error::Invalid(format!("{}: the scene has no video camera", dir.display())))?;
        let to_f32 = |img: &Vec<u8>| img.iter().map(|&b| b as f32 / 255.0).collect::<Vec<f32>>();
        let sup = &scene.cameras.supervision;
        let views = options.views.min(sup.len());
        let per_frame = sup.len();
        let views = GenerationViews {
            input,
            input_truth: scene.video.iter().map(to_f32).collect(),
            novel: sup[..views].to_vec(),
            novel_truth: (0..FRAMES)
                .map(|f| (0..views).map(|v| to_f32(&scene.supervision[f * per_frame + v])).collect())
                .collect(),
            background: scene.meta.background,
        };
        let (made, stored) = token_pair(gpu, models, scenes, i, &options.spec)?;
        let cloud: Vec<f32> = scene.points.iter().flatten().copied().collect();
        let cloud = (options.source == VoxelSource::Input).then_some(cloud.as_slice());
        let seed = options.spec.seed;
        let mut generated = Decoding::from_tokens(&models.ae, made, cloud, seed)?;
        let mut encoded = Decoding::from_tokens(&models.ae, stored, cloud, seed)?;
        if let Some(d) = options.voxel_decoder {
            generated = generated.with_voxel_decoder(d)?;
            encoded = encoded.with_voxel_decoder(d)?;
        }
        let keep = |f: usize| options.kept.contains(&f);
        let r = velox_models::eval::generation::evaluate_scene(
            &name,
            &generated,
            &encoded,
            options.source,
            &options.sampling,
            &options.frames,
            &views,
            &keep,
            &mut |fr| observer.renders(&name, &views, fr),
        )?;
        observer.done(&name, &views)?;
        results.push(r);
    }
    Ok(results)
}

/// A cloth scene's result and its frame time.
pub struct ClothResult {
    pub scene: ClothScene,
    /// Seconds between frames of the simulation the scene records.
    pub frame_seconds: f64,
}

/// What the cloth evaluation tells as it goes.
pub trait ClothObserver {
    /// Scene `name` starts.
    fn scene(&mut self, _name: &str) {}
    /// Frame `frame` of the surface decoded from the `tokens` (each scene decodes its frames
    /// twice: generated, then encoded), as xyz rows.
    fn frame(&mut self, _tokens: ClothTokens, _frame: usize, _points: &[f32]) {}
}

/// Which tokens a cloth scene's surface was decoded from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ClothTokens {
    /// The generator's, from the scene's condition.
    Generated,
    /// The encoder's, from the scene's cloud (what the generator learned to make).
    Encoded,
}

/// The height of the centre of mass along gravity, frame by frame, of the surface decoded from
/// the generator's tokens and from the encoder's, against the simulation each cloth scene
/// records (`cloth.json`, written by `velox data cloth`; see `velox_models::eval::cloth`).
pub fn cloth(
    gpu: &Gpu,
    models: &GeneratorModels,
    scenes: &TokenScenes,
    count: usize,
    spec: &GenerateSpec,
    sampling: &Sampling,
    observer: &mut dyn ClothObserver,
) -> Result<Vec<ClothResult>> {
    let mut results = Vec::with_capacity(count);
    for i in 0..count.min(scenes.len()) {
        let dir = &scenes.dirs()[i];
        let name = scenes.name(i);
        observer.scene(&name);
        let path = dir.join("cloth.json");
        let text = std::fs::read_to_string(&path).map_err(|e| {
            Error::Io(format!("{}: {e} (not a cloth scene? `velox data cloth` writes it)", path.display()))
        })?;
        let record: ClothRecord =
            serde_json::from_str(&text).map_err(|e| Error::Invalid(format!("{}: {e}", path.display())))?;
        let good = record.centre_of_mass.len() == FRAMES
            && record.centre_of_mass.iter().flatten().chain(&record.up).all(|v| v.is_finite())
            && record.frame_seconds.is_finite()
            && record.frame_seconds > 0.0;
        if !good {
            return Err(Error::Invalid(format!(
                "{}: needs {FRAMES} finite centres of mass, a finite up vector and a positive frame time",
                path.display()
            )));
        }
        let up = record.up.map(|v| v as f64);
        let simulated =
            heights(&record.centre_of_mass.iter().map(|c| c.map(|v| v as f64)).collect::<Vec<_>>(), up)?;
        let (made, stored) = token_pair(gpu, models, scenes, i, spec)?;
        let mut decoded = Vec::new();
        for (tokens, which) in [(made, ClothTokens::Generated), (stored, ClothTokens::Encoded)] {
            let d = Decoding::from_tokens(&models.ae, tokens, None, spec.seed)?;
            let mut centres = Vec::with_capacity(FRAMES);
            for f in 0..FRAMES {
                let points = d.surface_points(f, sampling)?;
                centres.push(centre_of_mass(&points)?);
                observer.frame(which, f, &points);
            }
            decoded.push(heights(&centres, up)?);
        }
        let encoded = decoded.pop().expect("two decodings");
        let generated = decoded.pop().expect("two decodings");
        let scene = ClothScene::new(&name, generated, encoded, simulated)?;
        results.push(ClothResult { scene, frame_seconds: record.frame_seconds as f64 });
    }
    Ok(results)
}
