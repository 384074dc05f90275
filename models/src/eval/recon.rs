//! Reconstruction quality of a trained autoencoder on held-out scenes (paper, Metrics: PSNR,
//! SSIM, Chamfer), as `velox eval recon` reports it.
//!
//! For each scene, the whole cloud is encoded once ([`Decoding::encode`], queries from the
//! seed); then every `frame_step`-th frame that has points is decoded, with the seed rule of
//! [`crate::velox::decode`]:
//! - images: the frame's Gaussians are rendered (black background, as the data's images) from
//!   the first `views` supervision cameras and compared with the ground-truth images by PSNR
//!   and SSIM ([`crate::metrics`]). The Gaussian decoder's queries are the occupied voxels of
//!   each of `voxels`' sources, side by side, as the paper's ablation compares them: a voxel
//!   decoder's prediction ([`VoxelSource::Predicted`]), the cloud's points of that frame, as in
//!   training ([`VoxelSource::Input`]), or the decoded surface samples below
//!   ([`VoxelSource::Surface`]); the first source's figures are the headline ones;
//! - geometry: `points` surface points sampled from the tokens against `points` of the frame's
//!   input points (evenly strided, [`subsample`]): symmetric Chamfer distance, squared
//!   distances in the data's [-1, 1]^3 units ([`chamfer`] says why that form). Beside it, the
//!   floor ("GT halves", the paper's "Chamfer oracle"): two disjoint `points`-point samples of
//!   the frame's input points (the even and odd points of `2 points` of them; fewer where the
//!   frame has fewer than `2 points`), the distance two samplings of the truth at the compared
//!   density sit apart.
//!
//! A scene's figures are the means over its frames (PSNR and SSIM over every frame and view);
//! the overall figures are the means over scenes. Up to `images` (frame, view) pairs per scene,
//! spread evenly over the evaluated ones, are handed to the observer as side-by-side images
//! (ground truth | ours) to keep.

use std::time::Instant;

use serde::Serialize;
use velox_engine::ops::raster::{render, GaussianData};
use velox_engine::{Error, Result};

use crate::metrics::{chamfer, psnr, ssim, subsample};
use crate::train::source::{prefetch, SampleSource};
use crate::velox::autoencoder::{tau_of, Autoencoder, TrainScene, FRAMES};
use crate::velox::decode::{sampler_name, Decoding, Sampling, VoxelSource};
use crate::velox::voxels::VoxelDecoder;
use velox_io::cloud::CHANNELS;

/// How to evaluate.
#[derive(Clone, Debug)]
pub struct ReconOptions {
    /// Supervision views per frame (the first V; `None`: all of a scene's views).
    pub views: Option<usize>,
    /// Evaluate every Nth frame (0, N, 2N, ...).
    pub frame_step: usize,
    /// The surface sampler, and the points on each side of the Chamfer distance.
    pub sampling: Sampling,
    /// Where the Gaussian decoder's voxels come from: each source is measured (at least one).
    pub voxels: Vec<VoxelSource>,
    /// Side-by-side images kept per scene.
    pub images: usize,
    /// Seed of the encoder's queries and the sampler's noise.
    pub seed: u64,
}

/// What an evaluation tells as it goes; the library writes no files itself.
pub trait ReconObserver {
    /// Scene `name` starts.
    fn scene(&mut self, _name: &str) {}
    /// One more of the `frame_step`-th frames is done (or skipped, having no points).
    fn frame(&mut self) {}
    /// A side-by-side image (ground truth | ours, `[height, 2 width, 3]` RGB in [0, 1]) of a
    /// frame and view of scene `scene`, chosen to be kept: returns the name the report lists
    /// it under (a file written, say), or `None` to list nothing.
    fn image(
        &mut self,
        _scene: &str,
        _frame: usize,
        _view: usize,
        _rgb: &[f32],
        _width: usize,
        _height: usize,
    ) -> Result<Option<String>> {
        Ok(None)
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct ViewMetrics {
    pub view: usize,
    pub psnr: f64,
    pub ssim: f64,
}

/// A frame's images decoded from one source of voxels.
#[derive(Clone, Debug, Serialize)]
pub struct SourceMetrics {
    pub source: VoxelSource,
    pub voxels: usize,
    pub gaussians: usize,
    pub psnr: f64,
    pub ssim: f64,
}

/// A scene's or the run's mean images from one source of voxels.
#[derive(Clone, Debug, Serialize)]
pub struct SourceMean {
    pub source: VoxelSource,
    pub psnr: f64,
    pub ssim: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct FrameMetrics {
    pub frame: usize,
    pub tau: f32,
    pub voxels: usize,
    pub gaussians: usize,
    pub chamfer: f64,
    /// The ground truth's Chamfer distance between its own even and odd points: what two
    /// samples of the true surface at this density score, so a floor the model cannot beat.
    pub chamfer_gt_halves: f64,
    pub psnr: f64,
    pub ssim: f64,
    pub views: Vec<ViewMetrics>,
    /// Every source's images (the first is the one above).
    pub sources: Vec<SourceMetrics>,
}

#[derive(Clone, Debug, Serialize)]
pub struct SceneMetrics {
    pub name: String,
    pub dir: String,
    pub points: usize,
    pub psnr: f64,
    pub ssim: f64,
    pub chamfer: f64,
    pub chamfer_gt_halves: f64,
    pub seconds: f64,
    pub images: Vec<String>,
    pub sources: Vec<SourceMean>,
    pub frames: Vec<FrameMetrics>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Mean {
    pub psnr: f64,
    pub ssim: f64,
    pub chamfer: f64,
    pub chamfer_gt_halves: f64,
    pub sources: Vec<SourceMean>,
}

/// Every number of an evaluation (what `eval.json` holds, with the checkpoint and the data).
#[derive(Clone, Debug, Serialize)]
pub struct ReconReport {
    pub config: String,
    pub precision: &'static str,
    pub device: String,
    pub voxels: Vec<VoxelSource>,
    pub frame_step: usize,
    pub chamfer_points: usize,
    pub sampler: &'static str,
    pub steps: usize,
    pub chamfer_units: &'static str,
    pub mean: Mean,
    pub scenes: Vec<SceneMetrics>,
    pub seconds: f64,
}

fn mean(v: impl IntoIterator<Item = f64>) -> f64 {
    let (sum, n) = v.into_iter().fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    sum / n.max(1) as f64
}

/// The frames evaluated: 0, `frame_step`, 2 `frame_step`...
pub fn frames(frame_step: usize) -> Vec<usize> {
    (0..FRAMES).step_by(frame_step.max(1)).collect()
}

/// Evaluates `ae` on every scene of `scenes` (read one ahead on another thread), as the
/// module docs say.
pub fn evaluate<S>(
    ae: &Autoencoder,
    voxel_decoder: Option<&VoxelDecoder>,
    scenes: &S,
    options: &ReconOptions,
    observer: &mut dyn ReconObserver,
) -> Result<ReconReport>
where
    S: SampleSource<Sample = TrainScene>,
{
    if options.voxels.is_empty() {
        return Err(Error::Invalid("an evaluation needs at least one source of voxels".into()));
    }
    let start = Instant::now();
    let results = std::thread::scope(|scope| {
        let incoming = prefetch(scope, scenes, 0..scenes.len(), 1)?;
        let mut results = Vec::with_capacity(scenes.len());
        for index in 0..scenes.len() {
            let raw = incoming.recv().map_err(|_| Error::Io("the scene-reading thread stopped".into()))??;
            let scene = scenes.prepare(raw)?;
            results.push(evaluate_scene(
                ae,
                voxel_decoder,
                &scene,
                &scenes.name(index),
                &scenes.location(index),
                options,
                observer,
            )?);
        }
        Ok::<_, Error>(results)
    })?;
    Ok(ReconReport {
        config: ae.cfg.name.clone(),
        precision: ae.precision().name(),
        device: ae.store.flat_params().gpu().caps().name.clone(),
        voxels: options.voxels.clone(),
        frame_step: options.frame_step,
        chamfer_points: options.sampling.points,
        sampler: sampler_name(options.sampling.sampler),
        steps: options.sampling.steps,
        chamfer_units: "mean squared distance, both directions summed, in the data's [-1, 1]^3 coordinates",
        mean: Mean {
            psnr: mean(results.iter().map(|s| s.psnr)),
            ssim: mean(results.iter().map(|s| s.ssim)),
            chamfer: mean(results.iter().map(|s| s.chamfer)),
            chamfer_gt_halves: mean(results.iter().map(|s| s.chamfer_gt_halves)),
            sources: source_means(&options.voxels, results.iter().flat_map(|s| &s.frames)),
        },
        scenes: results,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// One scene's metrics; errors name the scene's folder.
fn evaluate_scene(
    ae: &Autoencoder,
    voxel_decoder: Option<&VoxelDecoder>,
    scene: &TrainScene,
    name: &str,
    dir: &str,
    options: &ReconOptions,
    observer: &mut dyn ReconObserver,
) -> Result<SceneMetrics> {
    let named = |e: Error| match e {
        Error::Invalid(why) => Error::Invalid(format!("{dir}: {why}")),
        other => other,
    };
    observer.scene(name);
    let t0 = Instant::now();
    let gpu = scene.cloud.gpu();
    let mut decoding = Decoding::encode(ae, &scene.cloud_host, options.seed).map_err(named)?;
    if let Some(d) = voxel_decoder {
        decoding = decoding.with_voxel_decoder(d)?;
    }
    let cams = &scene.cameras;
    let views = options.views.map_or(cams.len(), |v| v.min(cams.len()));
    let frames = frames(options.frame_step);
    // The (frame, view) pairs kept as side-by-side images, spread evenly.
    let pairs = frames.iter().filter(|&&f| !decoding.input_points(f).is_empty()).count() * views;
    let keep = options.images.min(pairs);
    let chosen: Vec<usize> = (0..keep).map(|i| i * pairs / keep.max(1)).collect();
    let mut images = Vec::new();
    let mut pair = 0;
    let mut results = Vec::new();
    for &f in &frames {
        observer.frame();
        let truth_points = decoding.input_points(f);
        if truth_points.is_empty() {
            continue;
        }
        let samples = decoding.surface_points(f, &options.sampling)?;
        let rows = |v: &[f32]| v.chunks(3).map(|p| [p[0], p[1], p[2]]).collect::<Vec<[f32; 3]>>();
        let n = options.sampling.points;
        let truth = subsample(&rows(truth_points), n);
        let cd = chamfer(&subsample(&rows(&samples), n), &truth);
        // The floor at the density the model is compared at: two disjoint samples of n points
        // of the truth (the even and odd points of 2n), as the paper's "Chamfer oracle".
        let pool = subsample(&rows(truth_points), 2 * n);
        let halves: [Vec<[f32; 3]>; 2] = [0, 1].map(|h| pool.iter().skip(h).step_by(2).copied().collect());
        let floor = chamfer(&halves[0], &halves[1]);
        let mut sources = Vec::with_capacity(options.voxels.len());
        let mut first_views = Vec::new();
        for (k, &source) in options.voxels.iter().enumerate() {
            let centres = match source {
                VoxelSource::Input => decoding.cloud_voxels(f),
                VoxelSource::Surface => decoding.surface_voxels(&samples, f),
                VoxelSource::Predicted => decoding.predicted_voxels(f).map_err(named)?,
            };
            // No voxels (a voxel decoder that predicts none, say) draw the background alone.
            let g = if centres.is_empty() {
                GaussianData::default().upload(gpu)?
            } else {
                decoding.gaussians(f, &centres)?
            };
            let mut view_metrics = Vec::new();
            for (v, cam) in cams.iter().enumerate().take(views) {
                let rendered = render(gpu, &g, cam, scene.background)?;
                let ours: Vec<f32> =
                    rendered.image.rgb.read::<f32>()?.iter().map(|v| v.clamp(0.0, 1.0)).collect();
                let gt = &scene.images[f * cams.len() + v];
                let (w, h) = (cam.width as usize, cam.height as usize);
                view_metrics.push(ViewMetrics {
                    view: v,
                    psnr: psnr(&ours, gt),
                    ssim: ssim(&ours, gt, h, w, 3),
                });
                // The side-by-side images show the first source.
                if k == 0 {
                    if chosen.contains(&pair) {
                        if let Some(image) =
                            observer.image(name, f, v, &side_by_side(gt, &ours, w, h), w, h)?
                        {
                            images.push(image);
                        }
                    }
                    pair += 1;
                }
            }
            sources.push(SourceMetrics {
                source,
                voxels: centres.len() / 3,
                gaussians: g.len(),
                psnr: mean(view_metrics.iter().map(|m| m.psnr)),
                ssim: mean(view_metrics.iter().map(|m| m.ssim)),
            });
            if k == 0 {
                first_views = view_metrics;
            }
        }
        let first = &sources[0];
        results.push(FrameMetrics {
            frame: f,
            tau: tau_of(f),
            voxels: first.voxels,
            gaussians: first.gaussians,
            chamfer: cd,
            chamfer_gt_halves: floor,
            psnr: first.psnr,
            ssim: first.ssim,
            views: first_views,
            sources,
        });
    }
    let all_views = || results.iter().flat_map(|f| f.views.iter());
    Ok(SceneMetrics {
        name: name.to_string(),
        dir: dir.to_string(),
        points: scene.cloud_host.len() / CHANNELS,
        psnr: mean(all_views().map(|m| m.psnr)),
        ssim: mean(all_views().map(|m| m.ssim)),
        chamfer: mean(results.iter().map(|f| f.chamfer)),
        chamfer_gt_halves: mean(results.iter().map(|f| f.chamfer_gt_halves)),
        seconds: t0.elapsed().as_secs_f64(),
        images,
        sources: source_means(&options.voxels, results.iter()),
        frames: results,
    })
}

/// Each source's PSNR and SSIM, the means over `frames` (each frame's own mean over views).
fn source_means<'a>(
    sources: &[VoxelSource],
    frames: impl Iterator<Item = &'a FrameMetrics> + Clone,
) -> Vec<SourceMean> {
    sources
        .iter()
        .enumerate()
        .map(|(k, &source)| SourceMean {
            source,
            psnr: mean(frames.clone().map(|f| f.sources[k].psnr)),
            ssim: mean(frames.clone().map(|f| f.sources[k].ssim)),
        })
        .collect()
}

/// Ground truth on the left, ours on the right, `[h, 2w, 3]`.
fn side_by_side(gt: &[f32], ours: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(2 * gt.len());
    for y in 0..h {
        out.extend_from_slice(&gt[3 * w * y..3 * w * (y + 1)]);
        out.extend_from_slice(&ours[3 * w * y..3 * w * (y + 1)]);
    }
    out
}
