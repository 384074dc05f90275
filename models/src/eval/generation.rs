//! Generation quality (paper, video-to-4D and image-to-4D tables: PSNR and SSIM on the
//! conditioning view and on novel views), as `velox eval generation` reports it.
//!
//! For each scene, the generator's tokens (from the scene's conditioning video) and the
//! encoder's tokens of the scene (what the generator learned to make: its ceiling) are decoded
//! the same way, every chosen frame's Gaussians over the occupied voxels of one source (a voxel
//! decoder's prediction from each token set, or the scene cloud's voxels for both), rendered
//! on a black background from the conditioning camera and from novel views (the scene's
//! supervision cameras), and compared with the ground-truth images by PSNR and SSIM
//! ([`crate::metrics`]). A scene's figures are means over its frames (and views); the report's
//! means are over scenes. LPIPS, CLIP similarity and FVD need pretrained networks this
//! project does not ship, so they are not reported.

use serde::Serialize;
use velox_engine::ops::raster::{render, Camera, GaussianData};
use velox_engine::{Error, Gpu, Result};

use crate::metrics::{psnr, ssim};
use crate::velox::decode::{Decoding, Sampling, VoxelSource};

/// Where a scene is seen from, and the truth there: the conditioning camera with its frames
/// (`input_truth[f]`, RGB in [0, 1]), and novel cameras with theirs (`novel_truth[f][v]`).
pub struct GenerationViews {
    pub input: Camera,
    pub input_truth: Vec<Vec<f32>>,
    pub novel: Vec<Camera>,
    pub novel_truth: Vec<Vec<Vec<f32>>>,
    /// The truth's background, which the renders are drawn on.
    pub background: [f32; 3],
}

/// Mean PSNR (dB) and SSIM of a set of images.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct ImageScores {
    pub psnr: f64,
    pub ssim: f64,
}

/// One token set's scores on the conditioning view and on the novel views.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct ViewScores {
    pub input: ImageScores,
    pub novel: ImageScores,
}

/// A scene's scores: the generator's tokens and the encoder's, side by side.
#[derive(Clone, Debug, Serialize)]
pub struct GenerationScene {
    pub scene: String,
    pub generated: ViewScores,
    pub encoded: ViewScores,
    pub frames: Vec<usize>,
    /// Occupied voxels per frame the generator's Gaussians were decoded from.
    pub voxels: Vec<usize>,
    /// The generator's tokens against the encoder's: `sum (g - e)^2 / sum (e - mean e)^2`
    /// (0: the same tokens; 1: no better than the encoder's mean token; tokens of two unrelated
    /// scenes score about 2).
    pub token_nmse: f64,
}

/// The renders of one frame: per view (input first), the truth, the generator's and the
/// encoder's images.
pub struct FrameRenders {
    pub frame: usize,
    pub views: Vec<[Vec<f32>; 3]>,
}

fn mean(v: impl IntoIterator<Item = f64>) -> f64 {
    let (s, n) = v.into_iter().fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    s / n.max(1) as f64
}

/// Sums of PSNR and SSIM over images, for their means.
#[derive(Default)]
struct Sums {
    psnr: f64,
    ssim: f64,
    n: usize,
}

impl Sums {
    fn add(&mut self, img: &[f32], truth: &[f32], h: usize, w: usize) {
        self.psnr += psnr(img, truth);
        self.ssim += ssim(img, truth, h, w, 3);
        self.n += 1;
    }

    fn mean(&self) -> ImageScores {
        let n = self.n.max(1) as f64;
        ImageScores { psnr: self.psnr / n, ssim: self.ssim / n }
    }
}

/// Renders `g` from `cam` on `background`, clamped to [0, 1].
pub fn rendered(
    gpu: &Gpu,
    g: &velox_engine::ops::raster::Gaussians,
    cam: &Camera,
    background: [f32; 3],
) -> Result<Vec<f32>> {
    let r = render(gpu, g, cam, background)?;
    Ok(r.image.rgb.read::<f32>()?.iter().map(|v| v.clamp(0.0, 1.0)).collect())
}

/// Scores `generated` and `encoded` (decodings of one scene) at `frames` against `views`, the
/// voxels from `source`; `keep(frame)` says which frames' renders to hand to `renders`.
#[allow(clippy::too_many_arguments)]
pub fn evaluate_scene(
    scene: &str,
    generated: &Decoding,
    encoded: &Decoding,
    source: VoxelSource,
    sampling: &Sampling,
    frames: &[usize],
    views: &GenerationViews,
    keep: &dyn Fn(usize) -> bool,
    renders: &mut dyn FnMut(FrameRenders) -> Result<()>,
) -> Result<GenerationScene> {
    let gpu = generated.tokens().gpu().clone();
    let cams: Vec<&Camera> = std::iter::once(&views.input).chain(&views.novel).collect();
    // Per token set (generated, encoded), per view kind (input, novel).
    let mut sums: [[Sums; 2]; 2] = Default::default();
    let mut voxels = Vec::with_capacity(frames.len());
    for &f in frames {
        let truth_of = |v: usize| -> Result<&[f32]> {
            let t = if v == 0 {
                views.input_truth.get(f)
            } else {
                views.novel_truth.get(f).and_then(|t| t.get(v - 1))
            };
            t.map(Vec::as_slice).ok_or_else(|| {
                Error::Invalid(format!("scene {scene}: no ground truth for frame {f}, view {v}"))
            })
        };
        let mut frame_images: Vec<[Vec<f32>; 3]> = cams.iter().map(|_| Default::default()).collect();
        for (which, decoding) in [generated, encoded].into_iter().enumerate() {
            let centres = decoding.voxels(f, source, sampling).or_else(|e| match source {
                // A voxel decoder may predict nothing for poor tokens: that frame is black.
                VoxelSource::Predicted => Ok(Vec::new()),
                _ => Err(e),
            })?;
            if which == 0 {
                voxels.push(centres.len() / 3);
            }
            let g = if centres.is_empty() {
                GaussianData::default().upload(&gpu)?
            } else {
                decoding.gaussians(f, &centres)?
            };
            for (v, cam) in cams.iter().enumerate() {
                let img = rendered(&gpu, &g, cam, views.background)?;
                let truth = truth_of(v)?;
                if img.len() != truth.len() {
                    return Err(Error::Invalid(format!(
                        "scene {scene}: frame {f} view {v}: the truth has {} values, the camera renders {}",
                        truth.len(),
                        img.len()
                    )));
                }
                let (h, w) = (cam.height as usize, cam.width as usize);
                sums[which][(v > 0) as usize].add(&img, truth, h, w);
                if keep(f) {
                    frame_images[v][0] = truth.to_vec();
                    frame_images[v][1 + which] = img;
                }
            }
        }
        if keep(f) {
            renders(FrameRenders { frame: f, views: frame_images })?;
        }
    }
    let (g, e): (Vec<f32>, Vec<f32>) = (generated.tokens().read()?, encoded.tokens().read()?);
    let e64: Vec<f64> = e.iter().map(|&v| v as f64).collect();
    let token_nmse = velox_engine::stats::nmse(&g, &e64);
    let view_scores = |s: &[Sums; 2]| ViewScores { input: s[0].mean(), novel: s[1].mean() };
    Ok(GenerationScene {
        scene: scene.to_string(),
        generated: view_scores(&sums[0]),
        encoded: view_scores(&sums[1]),
        frames: frames.to_vec(),
        voxels,
        token_nmse,
    })
}

/// Means over scenes.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct GenerationMean {
    pub generated: ViewScores,
    pub encoded: ViewScores,
    pub token_nmse: f64,
}

impl GenerationMean {
    pub fn of(scenes: &[GenerationScene]) -> GenerationMean {
        let avg = |f: &dyn Fn(&GenerationScene) -> f64| mean(scenes.iter().map(f));
        let set = |g: &dyn Fn(&GenerationScene) -> ViewScores| ViewScores {
            input: ImageScores { psnr: avg(&|s| g(s).input.psnr), ssim: avg(&|s| g(s).input.ssim) },
            novel: ImageScores { psnr: avg(&|s| g(s).novel.psnr), ssim: avg(&|s| g(s).novel.ssim) },
        };
        GenerationMean {
            generated: set(&|s| s.generated),
            encoded: set(&|s| s.encoded),
            token_nmse: avg(&|s| s.token_nmse),
        }
    }
}
