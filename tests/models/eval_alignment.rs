//! Every evaluation scores each frame, view and scene against its own truth: `eval recon` (PSNR,
//! SSIM and Chamfer per frame), `eval voxels`, `eval tracking`, `eval generation` and `eval
//! cloth`, in the models' functions (`velox_models::eval`) and scene by scene as the commands run
//! them (`velox_tasks::evaluate`). The scenes move (procedural scenes 3 and 8: their frames and
//! views differ visibly, which each test checks), and each expected figure is worked out here:
//! from the autoencoder's own calls with the frame's own time, points and views, picked out of
//! the scene's files by this file's own indexing, or from an oracle that makes it known (a truth
//! equal to frame f's prediction scores perfectly for frame f, and measurably worse against
//! frame f + 1, another view or the other scene). An evaluation that shifted or swapped frames,
//! views or scenes fails here.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use velox_models::Model;

use crate::common;
use common::*;
use velox::data::cloth::{up, ClothRecord, GarmentKind};
use velox::data::format::{read_occupancy, write_scene};
use velox::data::{procedural, read_scene, SynthOptions};
use velox::engine::ops::raster::{render, Camera, GaussianData};
use velox::models::config::{AutoencoderConfig, GeneratorConfig, TrackerConfig, VoxelConfig};
use velox::models::eval::cloth::{centre_of_mass, heights, rmse, ClothScene};
use velox::models::eval::generation::{evaluate_scene as generation_scene, FrameRenders, GenerationViews};
use velox::models::eval::recon::{evaluate, ReconObserver, ReconOptions};
use velox::models::eval::tracking::{
    evaluate_scene as tracking_scene, Scaling, TrackingMetrics, TrackingReport, TrackingScene,
};
use velox::models::eval::voxels::{evaluate_scene as voxels_scene, VoxelMetrics};
use velox::models::metrics::{chamfer, psnr, ssim, subsample};
use velox::models::velox::autoencoder::{tau_of, Autoencoder, FRAMES};
use velox::models::velox::decode::{Decoding, Sampling, VoxelSource};
use velox::models::velox::generator::{GenerateSpec, Generator};
use velox::models::velox::surface::{SampleSpec, Sampler};
use velox::models::velox::tokens::{read_scene_file, scene_file, CloudSource};
use velox::models::velox::tracker::{Track, Tracker};
use velox::models::velox::voxels::{VoxelDecoder, FRAME_WORDS};
use velox::tasks::encode::{encode_dataset, EncodeOptions};
use velox::tasks::evaluate::{
    ClothObserver, ClothTokens, GenerationObserver, GenerationOptions, TrackingObserver, VoxelObserver,
};
use velox::tasks::generate::GeneratorModels;
use velox::tasks::{SceneFolders, TokenScenes, TrackScenes};

/// The seed of every evaluation here (the encoder's queries, the samplers' noise).
const SEED: u64 = 5;

/// Two moving procedural scenes (`DATA/scene_00000` and `_00001`, seeds 3 and 8, 16 px: 25
/// supervision views and a video with 8 tracks), a tiny autoencoder with random weights (every
/// part of it then reads the frame time and the voxels, so frames decode differently), and its
/// tokens of both scenes' clouds (`DATA/tokens`) and videos (`DATA/tokens-video`).
struct Fixture {
    data: PathBuf,
    ae: PathBuf,
}

fn fixture() -> &'static Fixture {
    static DIR: OnceLock<Fixture> = OnceLock::new();
    DIR.get_or_init(|| {
        let gpu = gpu();
        let dir = std::env::temp_dir().join(format!("velox-eval-alignment-{}", std::process::id()));
        let data = dir.join("data");
        for (i, seed) in [3u64, 8].into_iter().enumerate() {
            let (_, mesh) = procedural::scene(seed, None).unwrap();
            let opts =
                SynthOptions { res: 16, points: 3000, supersample: 1, tracks: 8, ..Default::default() };
            let scene = data.join(format!("scene_{i:05}"));
            write_scene(&gpu, &mesh, "test", None, seed, &opts, &scene, &mut |_| {}).unwrap();
        }
        let ae = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 1).unwrap();
        randomize_params(&ae.store, 6, 0.5);
        let path = dir.join("ae.safetensors");
        ae.save(&path).unwrap();
        for source in [CloudSource::Points, CloudSource::Video] {
            let options = EncodeOptions {
                checkpoint: path.clone(),
                data: data.clone(),
                out: None,
                seed: SEED,
                precision: Precision::F32,
                force: false,
                source,
                video_points: 2000,
            };
            encode_dataset(&gpu, &options, &mut ()).unwrap();
        }
        Fixture { data, ae: path }
    })
}

fn scene_dirs(f: &Fixture) -> [PathBuf; 2] {
    [0, 1].map(|i| f.data.join(format!("scene_{i:05}")))
}

/// A scene's cloud as host rows (x, y, z, r, g, b, tau).
fn cloud_of(dir: &Path) -> Vec<f32> {
    read_scene(dir, false).unwrap().points.iter().flatten().copied().collect()
}

/// xyz of the cloud's points of frame `f` (tau f / 100), picked out here.
fn points_of_frame(cloud: &[f32], f: usize) -> Vec<f32> {
    cloud.chunks(7).filter(|p| (p[6] * 100.0).round() as usize == f).flat_map(|p| p[..3].to_vec()).collect()
}

/// `tokens` decoded at frame `f` to Gaussians over the voxels of `points` (the autoencoder's
/// grid), rendered from `cam` on black and clamped to [0, 1]; black where there are no voxels.
fn render_frame(ae: &Autoencoder, tokens: &Tensor, points: &[f32], f: usize, cam: &Camera) -> Vec<f32> {
    let gpu = tokens.gpu();
    let tau = f as f32 / 100.0;
    let centres = ae.voxels_from_points(points, tau);
    let g = if centres.is_empty() {
        GaussianData::default().upload(gpu).unwrap()
    } else {
        ae.decode_gaussians(tokens, &centres, tau).unwrap()
    };
    render(gpu, &g, cam, [0.0; 3])
        .unwrap()
        .image
        .rgb
        .read::<f32>()
        .unwrap()
        .iter()
        .map(|v| v.clamp(0.0, 1.0))
        .collect()
}

/// Surface points of frame `f` sampled from `tokens` with the decodings' seed rule (frame f's
/// noise from `seed ^ ((f + 1) * 0x9e3779b97f4a7c15)`, `velox_models::velox::decode`).
fn surface_of_frame(ae: &Autoencoder, tokens: &Tensor, f: usize, s: &Sampling, seed: u64) -> Vec<f32> {
    let spec = SampleSpec {
        points: s.points,
        steps: s.steps,
        sampler: s.sampler,
        seed: seed ^ (f as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15),
        precision: Precision::F32,
    };
    ae.decode_points(tokens, f as f32 / 100.0, &spec).unwrap().read().unwrap()
}

fn rows(v: &[f32]) -> Vec<[f32; 3]> {
    v.chunks(3).map(|p| [p[0], p[1], p[2]]).collect()
}

fn rgb(img: &[u8]) -> Vec<f32> {
    img.iter().map(|&b| b as f32 / 255.0).collect()
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

/// A scene's stored tokens (read from its file here) on the device.
fn stored_tokens(gpu: &Gpu, token_dir: &Path, scene: &str) -> Tensor {
    read_scene_file(&scene_file(token_dir, scene)).unwrap().1.upload(gpu).unwrap()
}

/// Records the side-by-side images `eval recon` keeps.
#[derive(Default)]
struct KeptImages(Vec<(String, usize, usize, Vec<f32>)>);

impl ReconObserver for KeptImages {
    fn image(
        &mut self,
        scene: &str,
        frame: usize,
        view: usize,
        rgb: &[f32],
        _width: usize,
        _height: usize,
    ) -> velox::engine::Result<Option<String>> {
        self.0.push((scene.to_string(), frame, view, rgb.to_vec()));
        Ok(Some(format!("{scene}_f{frame}_v{view}")))
    }
}

/// `eval recon` on the two moving scenes, 2 of their 25 views, every 7th frame, voxels from
/// the cloud and from the surface: every frame's PSNR and SSIM per view are those of its own
/// render (the tokens decoded at its own time over its own points' voxels, or over its own
/// surface samples' voxels) against its own view's image (frame-major, 25 views a frame), its
/// Chamfer distance that of its own samples against its own points, every figure under its own
/// scene's name; the kept side-by-side images show the frame, view and scene they are listed
/// under. The same render against the next frame's image, the next view's or the other scene's
/// scores otherwise (checked), so would catch: frames, views or scenes shifted or swapped, the
/// images indexed with the views evaluated instead of the scene's (`f * views + v`), a frame
/// decoded at another frame's time or over another frame's voxels, the Chamfer truth of
/// another frame, a side-by-side image of another pair.
#[test]
fn recon_scores_each_frame_against_its_own_views_and_scene() {
    let gpu = gpu();
    let fx = fixture();
    let ae = Autoencoder::load(&gpu, &fx.ae).unwrap();
    let sampling = Sampling { points: 64, steps: 2, sampler: Sampler::Euler };
    let options = ReconOptions {
        views: Some(2),
        frame_step: 7,
        sampling,
        voxels: vec![VoxelSource::Input, VoxelSource::Surface],
        images: 4,
        seed: SEED,
    };
    let scenes = SceneFolders::open(&gpu, &fx.data).unwrap();
    let mut kept = KeptImages::default();
    let report = evaluate(&ae, None, &scenes, &options, &mut kept).unwrap();
    let dirs = scene_dirs(fx);
    let clouds = dirs.each_ref().map(|d| cloud_of(d));
    let images: Vec<Vec<Vec<f32>>> = dirs
        .iter()
        .map(|d| read_scene(d, true).unwrap().supervision.iter().map(|i| rgb(i)).collect())
        .collect();
    // Each scene draws its own supervision cameras.
    let cameras = dirs.each_ref().map(|d| read_scene(d, false).unwrap().cameras.supervision);
    let per_frame = cameras[0].len();
    assert_eq!((per_frame, cameras[1].len()), (25, 25));
    assert_ne!(cameras[0][0], cameras[1][0]);
    assert_eq!(report.scenes.len(), 2);
    let mut renders = std::collections::HashMap::new();
    let mut most_alike = 0.0f64;
    for (s, r) in report.scenes.iter().enumerate() {
        assert_eq!(r.name, format!("scene_{s:05}"));
        let tokens = ae.encode(&velox::io::cloud::upload(&gpu, &clouds[s]).unwrap(), SEED).unwrap();
        assert_eq!(r.frames.iter().map(|m| m.frame).collect::<Vec<_>>(), [0, 7, 14, 21]);
        for m in &r.frames {
            let f = m.frame;
            assert_eq!(m.tau, tau_of(f));
            let points = points_of_frame(&clouds[s], f);
            let samples = surface_of_frame(&ae, &tokens, f, &sampling, SEED);
            let cd = chamfer(&subsample(&rows(&samples), 64), &subsample(&rows(&points), 64));
            assert_eq!(m.chamfer, cd, "scene {s} frame {f}: Chamfer");
            let next = points_of_frame(&clouds[s], f + 1);
            assert_ne!(cd, chamfer(&subsample(&rows(&samples), 64), &subsample(&rows(&next), 64)));
            let inside: Vec<f32> =
                samples.chunks(3).filter(|p| p.iter().all(|v| v.abs() <= 1.0)).flatten().copied().collect();
            for (k, voxels_of) in [&points, &inside].into_iter().enumerate() {
                let (mut p, mut q) = (Vec::new(), Vec::new());
                for (v, cam) in cameras[s].iter().enumerate().take(2) {
                    let img = render_frame(&ae, &tokens, voxels_of, f, cam);
                    let truth = &images[s][f * per_frame + v];
                    p.push(psnr(&img, truth));
                    q.push(ssim(&img, truth, 16, 16, 3));
                    if k == 0 {
                        let got = &m.views[v];
                        assert_eq!(
                            (got.view, got.psnr, got.ssim),
                            (v, p[v], q[v]),
                            "scene {s} frame {f} view {v}"
                        );
                        // The next frame's image, the next view's and the other scene's
                        // differ from this one, and score this render otherwise.
                        for other in [
                            &images[s][(f + 1) * per_frame + v],
                            &images[s][f * per_frame + v + 1],
                            &images[1 - s][f * per_frame + v],
                        ] {
                            most_alike = most_alike.max(psnr(truth, other));
                            assert_ne!(psnr(&img, other), p[v], "scene {s} frame {f} view {v}");
                        }
                        renders.insert((s, f, v), img);
                    }
                }
                let source = &m.sources[k];
                assert_eq!(
                    (source.psnr, source.ssim),
                    (mean(&p), mean(&q)),
                    "scene {s} frame {f} source {k}"
                );
                if k == 0 {
                    assert_eq!((m.psnr, m.ssim), (mean(&p), mean(&q)));
                }
            }
        }
    }
    if verbose() {
        eprintln!("recon: another frame's, view's or scene's image is {most_alike:.1} dB from a frame's own at most");
    }
    assert!(most_alike < 50.0, "frames, views or scenes too alike to tell apart: {most_alike} dB");
    // Each kept image: the named frame and view of the named scene beside its render.
    assert_eq!(kept.0.len(), 8);
    for (name, f, v, side) in &kept.0 {
        let s = if name == "scene_00000" { 0 } else { 1 };
        let (truth, ours) = (&images[s][f * per_frame + v], &renders[&(s, *f, *v)]);
        for y in 0..16 {
            assert_eq!(
                &side[96 * y..96 * y + 48],
                &truth[48 * y..48 * y + 48],
                "{name} frame {f} view {v}: truth"
            );
            assert_eq!(
                &side[96 * y + 48..96 * (y + 1)],
                &ours[48 * y..48 * (y + 1)],
                "{name} frame {f} view {v}: ours"
            );
        }
    }
}

/// The tiny voxel decoder with random weights, for the fixture's tokens. Random weights put
/// most coarse cells' probabilities between 0.5 and 0.6: refining those above 0.55 keeps a few
/// hundred cells a frame (1500 to 2200 voxels), where the default 0.5 refines thousands.
fn random_voxel_decoder(gpu: &Gpu) -> VoxelDecoder {
    let cfg = VoxelConfig { token_dim: 8, cell_threshold: 0.55, ..VoxelConfig::tiny() };
    let decoder = VoxelDecoder::new(gpu, &cfg, 3).unwrap();
    randomize_params(&decoder.store, 4, 1.0);
    decoder
}

/// A voxel decoder with random weights, and as the truth its own prediction of every frame
/// (predicted one frame at a time): every evaluated frame (0, 5, ... 20) scores perfectly and
/// reports its own frame and prediction, and the same prediction against the next frame's
/// truth scores an IoU well below 1. Would catch: a frame predicted at another frame's time
/// (the index into the evaluated frames taken for the frame), scored against another frame's
/// words, or reported under another frame.
#[test]
fn voxels_scores_each_frame_against_its_own_occupancy() {
    let gpu = gpu();
    let decoder = random_voxel_decoder(&gpu);
    let cfg = &decoder.cfg;
    let tokens = Tensor::from_slice(&gpu, &[32, 8], &Rng::new(5).normal_vec(32 * 8)).unwrap();
    let truth: Vec<u64> = (0..FRAMES)
        .flat_map(|f| decoder.predict(&tokens, &[tau_of(f)]).unwrap().remove(0).occupancy)
        .collect();
    let of = |f: usize| &truth[f * FRAME_WORDS..(f + 1) * FRAME_WORDS];
    let r = voxels_scene(&decoder, "oracle", &tokens, &truth, 5).unwrap();
    assert_eq!(r.frames.iter().map(|m| m.frame).collect::<Vec<_>>(), [0, 5, 10, 15, 20]);
    let mut worst = 0.0f64;
    for m in &r.frames {
        let f = m.frame;
        assert_eq!(m.predicted, of(f), "frame {f}: the prediction");
        let (t, fp) = (m.metrics.true_voxels, m.metrics.predicted_voxels);
        assert!(t > 100.0, "frame {f}: {t} true voxels, too few to tell frames apart");
        assert_eq!(
            (m.metrics.iou, m.metrics.precision, m.metrics.recall, m.metrics.accuracy),
            (1.0, 1.0, 1.0, 1.0)
        );
        assert_eq!(fp, t);
        let next = VoxelMetrics::of(&m.predicted, of(f + 1), &[], cfg.cells).iou;
        worst = worst.max(next);
    }
    if verbose() {
        eprintln!("voxels: a frame's prediction against the next frame's truth: IoU {worst:.3} at best");
    }
    assert!(worst < 0.99, "the next frame's truth scores IoU {worst}");
    assert_eq!(r.mean.iou, 1.0);
}

/// Six tracks moving across a camera's view, and depth frames with an occluder that sweeps
/// across the image: the truth's visibility is the camera's depth test at each frame, so it
/// changes from frame to frame.
struct MovingTracks {
    camera: Camera,
    truth: Vec<Track>,
    visible: Vec<[bool; FRAMES]>,
    depth: Vec<Vec<f32>>,
}

fn moving_tracks() -> MovingTracks {
    // 2.5 in front of the scene's box, looking down +z.
    let camera = Camera { translation: [0.0, 0.0, 2.5], ..Camera::identity(50.0, 32, 24) };
    let truth: Vec<Track> = (0..6)
        .map(|i| {
            let (x, y, z) = (-0.6 + 0.2 * i as f32, 0.1 * (i % 3) as f32 - 0.1, -0.5 + 0.1 * i as f32);
            std::array::from_fn(|f| [x + 0.02 * f as f32, y - 0.01 * f as f32, z + 0.02 * f as f32])
        })
        .collect();
    // A wall at depth 10, and nearer it a band 8 pixels wide at depth 1 moving 1 pixel a frame.
    let depth: Vec<Vec<f32>> = (0..FRAMES)
        .map(|f| (0..32 * 24).map(|p| if (p % 32 + 32 - f % 32) % 32 < 8 { 1.0 } else { 10.0 }).collect())
        .collect();
    let visible = truth.iter().map(|t| std::array::from_fn(|f| camera.sees(t[f], &depth[f]))).collect();
    MovingTracks { camera, truth, visible, depth }
}

/// The truth's tracks as a prediction score perfectly (every point within every threshold,
/// visibility as the depth test of their own frame); each track predicted at half or a third of
/// its scale (its own factor) scores perfectly once `per_trajectory` rescales it by its own
/// query's depth; the next frame's point, or another track, scores below that; and
/// `evaluate_scene` reports the tracker, the static baseline and the truth each under its own
/// name. Would catch: a frame's visibility taken from another frame's depth, the truth's
/// visibility rows read against other tracks' or other frames' points, the per-track factor
/// of another track or another frame (the point's track read as `k % frames`, its query as
/// track `i`'s frame `i`), the tracker's figures reported as the baseline's.
#[test]
fn tracking_scores_each_track_and_frame_against_its_own_truth() {
    let m = moving_tracks();
    let changes = m.visible.iter().filter(|v| v.iter().any(|&s| s != v[0])).count();
    assert!(changes >= 3, "the occluder should hide tracks at some frames and not others ({changes})");
    let colours = vec![[0.5f32; 3]; 6];
    let scene = TrackingScene {
        truth: &m.truth,
        colours: &colours,
        visible: &m.visible,
        camera: &m.camera,
        depth: &m.depth,
    };
    let perfect = scene.metrics(&m.truth, Scaling::None).unwrap();
    assert_eq!((perfect.apd_visible, perfect.average_jaccard, perfect.occlusion_accuracy), (1.0, 1.0, 1.0));
    assert!(perfect.l2_all == 0.0 && (perfect.apd_all - 1.0).abs() < 1e-12, "{perfect:?}");
    // Each track at its own scale towards the camera: per_trajectory undoes it.
    let t = m.camera.translation;
    let scaled: Vec<Track> = m
        .truth
        .iter()
        .enumerate()
        .map(|(i, track)| {
            track.map(|p| std::array::from_fn(|k| (p[k] + t[k]) / (2.0 + (i % 2) as f32) - t[k]))
        })
        .collect();
    let rescaled = scene.metrics(&scaled, Scaling::PerTrajectory).unwrap();
    assert!(rescaled.apd_visible > 1.0 - 1e-12 && rescaled.l2_visible < 1e-5, "{rescaled:?}");
    assert!(scene.metrics(&scaled, Scaling::Median).unwrap().apd_visible < 0.9);
    let next: Vec<Track> =
        m.truth.iter().map(|t| std::array::from_fn(|f| t[(f + 1).min(FRAMES - 1)])).collect();
    let mut swapped = m.truth.clone();
    swapped.swap(0, 1);
    for (what, p) in [("the next frame's points", &next), ("two tracks swapped", &swapped)] {
        let s = scene.metrics(p, Scaling::None).unwrap();
        if verbose() {
            eprintln!("tracking, {what}: APD {:.3}, OA {:.3}", s.apd_visible, s.occlusion_accuracy);
        }
        assert!(s.apd_visible < 0.9, "{what}: APD {}", s.apd_visible);
    }
    // The whole scene's report: each method under its own name.
    let gpu = gpu();
    let tracker = Tracker::new(&gpu, &TrackerConfig { token_dim: 8, ..TrackerConfig::tiny() }, 2).unwrap();
    randomize_params(&tracker.store, 3, 0.5);
    let mut rng = Rng::new(9);
    let tokens = Tensor::from_slice(&gpu, &[16, 8], &rng.normal_vec(16 * 8)).unwrap();
    let points: Vec<f32> =
        (0..16).flat_map(|i| [rng.range(-1.0, 1.0) as f32, 0.0, 0.5, (i % 24) as f32 / 100.0]).collect();
    let token_points = Tensor::from_slice(&gpu, &[16, 4], &points).unwrap();
    let (report, predicted) =
        tracking_scene(&tracker, "moving", &tokens, &token_points, &scene, Scaling::Median).unwrap();
    let still: Vec<Track> = m.truth.iter().map(|t| [t[0]; FRAMES]).collect();
    assert_eq!(report.tracker, scene.metrics(&predicted, Scaling::Median).unwrap());
    assert_eq!(report.static_baseline, scene.metrics(&still, Scaling::Median).unwrap());
    assert_eq!(report.truth, scene.metrics(&m.truth, Scaling::Median).unwrap());
    assert_eq!(report.truth.apd_visible, 1.0);
    assert_ne!(report.tracker, report.static_baseline);
    assert_eq!((report.name.as_str(), report.queries), ("moving", 6));
}

/// `eval generation`'s scoring of one scene (scene 0 of the fixture, voxels from its cloud)
/// with a truth made known: every frame's input-view and novel-view truth is the encoder's
/// tokens' own render of that frame from that camera, so the encoded set scores perfectly (PSNR
/// +Inf, SSIM 1) and the generated set (scene 1's tokens, as a generator that made the wrong
/// scene) scores what its renders against those truths give, worked out here; the kept frame's
/// renders are its own frame's. The encoded render of a frame against the next frame's truth,
/// or another view's, scores finitely (the frames and views differ). Would catch: a frame
/// scored against another frame's truth, a view against another view's (the novel views'
/// index off by one), the input view counted among the novel ones, the two token sets' scores
/// swapped, a frame's Gaussians decoded at another frame.
#[test]
fn generation_scores_each_frame_and_view_against_its_own_truth() {
    let gpu = gpu();
    let fx = fixture();
    let ae = Autoencoder::load(&gpu, &fx.ae).unwrap();
    let dirs = scene_dirs(fx);
    let scene = read_scene(&dirs[0], false).unwrap();
    let cloud = cloud_of(&dirs[0]);
    let upload = |c: &[f32]| velox::io::cloud::upload(&gpu, c).unwrap();
    let (ours, theirs) =
        (ae.encode(&upload(&cloud), SEED).unwrap(), ae.encode(&upload(&cloud_of(&dirs[1])), SEED).unwrap());
    let cams: Vec<Camera> = std::iter::once(scene.cameras.video.unwrap())
        .chain(scene.cameras.supervision[..2].iter().copied())
        .collect();
    let points: Vec<Vec<f32>> = (0..FRAMES).map(|f| points_of_frame(&cloud, f)).collect();
    let truth: Vec<Vec<Vec<f32>>> = (0..FRAMES)
        .map(|f| cams.iter().map(|c| render_frame(&ae, &ours, &points[f], f, c)).collect())
        .collect();
    let views = GenerationViews {
        input: cams[0],
        input_truth: truth.iter().map(|t| t[0].clone()).collect(),
        novel: cams[1..].to_vec(),
        novel_truth: truth.iter().map(|t| t[1..].to_vec()).collect(),
        background: [0.0; 3],
    };
    let frames = [0, 5, 10, 15];
    let generated = Decoding::from_tokens(&ae, theirs.clone(), Some(&cloud), SEED).unwrap();
    let encoded = Decoding::from_tokens(&ae, ours.clone(), Some(&cloud), SEED).unwrap();
    let mut kept = Vec::new();
    let r = generation_scene(
        "scene_00000",
        &generated,
        &encoded,
        VoxelSource::Input,
        &Sampling::heun(64),
        &frames,
        &views,
        &|f| f == 10,
        &mut |fr: FrameRenders| {
            kept.push(fr);
            Ok(())
        },
    )
    .unwrap();
    for s in [r.encoded.input, r.encoded.novel] {
        assert!(s.psnr == f64::INFINITY && s.ssim == 1.0, "the encoded set against its own renders: {s:?}");
    }
    let (mut input, mut novel) = ((Vec::new(), Vec::new()), (Vec::new(), Vec::new()));
    let mut most_alike = 0.0f64;
    for &f in &frames {
        for (v, cam) in cams.iter().enumerate() {
            let img = render_frame(&ae, &theirs, &points[f], f, cam);
            let into = if v == 0 { &mut input } else { &mut novel };
            into.0.push(psnr(&img, &truth[f][v]));
            into.1.push(ssim(&img, &truth[f][v], 16, 16, 3));
            // How alike the next frame's truth and the next view's are to this one.
            most_alike = most_alike
                .max(psnr(&truth[f][v], &truth[f + 1][v]))
                .max(psnr(&truth[f][v], &truth[f][(v + 1) % 3]));
        }
    }
    if verbose() {
        eprintln!(
            "generation: the next frame's or view's truth is {most_alike:.1} dB from a frame's own at most"
        );
    }
    assert!(most_alike < 50.0, "frames or views too alike to tell apart: {most_alike} dB");
    assert_eq!((r.generated.input.psnr, r.generated.input.ssim), (mean(&input.0), mean(&input.1)));
    assert_eq!((r.generated.novel.psnr, r.generated.novel.ssim), (mean(&novel.0), mean(&novel.1)));
    assert!(r.generated.input.psnr.is_finite() && r.generated.novel.psnr.is_finite());
    assert_eq!(r.frames, frames);
    let counts: Vec<usize> =
        frames.iter().map(|&f| ae.voxels_from_points(&points[f], tau_of(f)).len() / 3).collect();
    assert_eq!(r.voxels, counts);
    assert_eq!(kept.len(), 1);
    assert_eq!(kept[0].frame, 10);
    for (v, [t, g, e]) in kept[0].views.iter().enumerate() {
        assert_eq!((t, e), (&truth[10][v], &truth[10][v]), "kept frame 10, view {v}");
        assert_eq!(g, &render_frame(&ae, &theirs, &points[10], 10, &cams[v]));
    }
}

/// `eval cloth`'s scoring with the truth made known: heights along a tilted up vector of a
/// falling centre of mass (worked out here as dot products), the generated heights equal to the
/// simulated ones (RMSE 0) and the encoded ones a frame late (the RMSE of the frame-to-frame
/// fall, worked out here). Would catch: heights compared with another frame's (an RMSE over
/// pairs shifted by one), the generated and encoded RMSEs swapped, the up vector's components
/// taken in another order.
#[test]
fn cloth_scores_each_frame_against_its_own_simulated_height() {
    let u = [0.5f64, 0.8, 0.1];
    let norm = (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt();
    let centres: Vec<[f64; 3]> = (0..FRAMES)
        .map(|f| [0.1 + 0.01 * f as f64, 0.6 - 0.002 * (f * f) as f64, -0.2 + 0.003 * f as f64])
        .collect();
    let simulated = heights(&centres, u).unwrap();
    for (f, c) in centres.iter().enumerate() {
        let want = (c[0] * u[0] + c[1] * u[1] + c[2] * u[2]) / norm;
        assert!((simulated[f] - want).abs() < 1e-12, "frame {f}: height {} against {want}", simulated[f]);
    }
    let late: Vec<f64> = (0..FRAMES).map(|f| simulated[f.saturating_sub(1)]).collect();
    let scene = ClothScene::new("falling", simulated.clone(), late.clone(), simulated.clone()).unwrap();
    assert_eq!(scene.rmse_generated, 0.0);
    let fall: Vec<f64> = (1..FRAMES).map(|f| simulated[f] - simulated[f - 1]).collect();
    let want = (fall.iter().map(|d| d * d).sum::<f64>() / FRAMES as f64).sqrt();
    assert!(
        (scene.rmse_encoded - want).abs() < 1e-12 && want > 0.01,
        "{} against {want}",
        scene.rmse_encoded
    );
    assert_eq!(
        (scene.generated.clone(), scene.encoded.clone(), scene.simulated.clone()),
        (simulated.clone(), late, simulated)
    );
    // The mean of points is their centre, frame by frame.
    let points = [0.0f32, 1.0, 2.0, 2.0, 3.0, 4.0];
    assert_eq!(centre_of_mass(&points).unwrap(), [1.0, 2.0, 3.0]);
    assert!(rmse(&[1.0, 2.0, 3.0], &[1.0, 2.0, 3.0]).unwrap() == 0.0);
}

// Scene by scene, as the commands run them (`velox_tasks::evaluate`), on the fixture's two
// scenes: each scene's figures are those of its own data, read here by its own folder.

/// Remembers which scenes an evaluation handed over, in order.
#[derive(Default)]
struct Seen {
    names: Vec<String>,
    occupancy: Vec<Vec<u64>>,
    tracks: Vec<(usize, String, Camera, Vec<Track>)>,
    renders: Vec<(String, usize, Vec<Vec<f32>>)>,
    surfaces: Vec<(ClothTokens, usize, [f64; 3])>,
}

impl VoxelObserver for Seen {
    fn scene(&mut self, name: &str) {
        self.names.push(name.to_string());
    }
    fn measured(
        &mut self,
        _scene: &velox::models::eval::voxels::SceneVoxels,
        occupancy: &[u64],
    ) -> velox::engine::Result<()> {
        self.occupancy.push(occupancy.to_vec());
        Ok(())
    }
}

impl TrackingObserver for Seen {
    fn scene(&mut self, name: &str) {
        self.names.push(name.to_string());
    }
    fn measured(
        &mut self,
        index: usize,
        name: &str,
        video: &velox::data::rgbd::RgbdVideo,
        scene: &TrackingScene,
        _predicted: &[Track],
    ) -> velox::engine::Result<()> {
        self.tracks.push((index, name.to_string(), video.camera, scene.truth.to_vec()));
        Ok(())
    }
}

impl GenerationObserver for Seen {
    fn scene(&mut self, name: &str) {
        self.names.push(name.to_string());
    }
    fn renders(
        &mut self,
        name: &str,
        _views: &GenerationViews,
        frame: FrameRenders,
    ) -> velox::engine::Result<()> {
        self.renders.push((
            name.to_string(),
            frame.frame,
            frame.views.into_iter().map(|[t, _, _]| t).collect(),
        ));
        Ok(())
    }
}

impl ClothObserver for Seen {
    fn scene(&mut self, name: &str) {
        self.names.push(name.to_string());
    }
    fn frame(&mut self, tokens: ClothTokens, frame: usize, points: &[f32]) {
        self.surfaces.push((tokens, frame, centre_of_mass(points).unwrap()));
    }
}

/// The voxel decoder and the tracker scene by scene: each scene's figures are those of its own
/// tokens with its own occupancy (the voxel decoder) and its own video, tracks and visibility
/// (the tracker), under its own name, and differ from the other scene's data. Would catch: a
/// scene measured with another scene's tokens, occupancy, video or tracks, or listed under
/// another's name.
#[test]
fn voxels_and_tracking_measure_each_scene_with_its_own_data() {
    let gpu = gpu();
    let fx = fixture();
    let dirs = scene_dirs(fx);
    let names = ["scene_00000", "scene_00001"];
    let decoder = random_voxel_decoder(&gpu);
    let scenes = TokenScenes::open(&gpu, &fx.data, None, Some(&fx.ae)).unwrap();
    let mut seen = Seen::default();
    let got = velox::tasks::evaluate::voxels(&decoder, &scenes, 2, 12, &mut seen).unwrap();
    assert_eq!(seen.names, names);
    let token_dir = fx.data.join("tokens");
    let own = |s: usize, o: usize| {
        let occupancy = read_occupancy(&dirs[o]).unwrap();
        voxels_scene(&decoder, names[s], &stored_tokens(&gpu, &token_dir, names[s]), &occupancy, 12).unwrap()
    };
    for s in 0..2 {
        let (r, want) = (&got.scenes[s], own(s, s));
        assert_eq!(r.name, names[s]);
        assert_eq!(seen.occupancy[s], read_occupancy(&dirs[s]).unwrap(), "scene {s}: the occupancy drawn");
        for (a, b) in r.frames.iter().zip(&want.frames) {
            assert_eq!((a.frame, a.metrics, &a.predicted), (b.frame, b.metrics, &b.predicted), "scene {s}");
        }
        // The other scene's occupancy scores otherwise.
        assert_ne!(want.mean, own(s, 1 - s).mean, "scene {s}: the scenes' occupancies score alike");
    }

    let tracker = Tracker::new(&gpu, &TrackerConfig { token_dim: 8, ..TrackerConfig::tiny() }, 2).unwrap();
    randomize_params(&tracker.store, 3, 0.5);
    let track_scenes = TrackScenes::open(&gpu, &fx.data, None, Some(&fx.ae)).unwrap();
    let mut seen = Seen::default();
    let got =
        velox::tasks::evaluate::tracking(&tracker, &track_scenes, 2, Scaling::Median, &mut seen).unwrap();
    assert_eq!((seen.names.clone(), got.left_out.len()), (names.map(String::from).to_vec(), 0));
    // Scene `s` measured on scene `o`'s video and tracks.
    let measure = |s: usize, o: usize| -> TrackingReport {
        let (sample, _) = track_scenes.load_with_visibility(s).unwrap();
        let (other, visible) = track_scenes.load_with_visibility(o).unwrap();
        let video = velox::data::rgbd::read_scene_video(&dirs[o]).unwrap();
        let scene = TrackingScene {
            truth: &other.tracks,
            colours: &other.colours,
            visible: &visible,
            camera: &video.camera,
            depth: &video.depth,
        };
        tracking_scene(&tracker, names[s], &sample.tokens, &sample.token_points, &scene, Scaling::Median)
            .unwrap()
            .0
    };
    for s in 0..2 {
        let (r, want) = (&got.scenes[s], measure(s, s));
        assert_eq!(r.name, names[s]);
        let same = |a: &TrackingReport, b: &TrackingReport| -> bool {
            let m = |x: &TrackingReport| -> [TrackingMetrics; 3] {
                [x.tracker.clone(), x.static_baseline.clone(), x.truth.clone()]
            };
            m(a) == m(b) && a.queries == b.queries
        };
        assert!(same(r, &want), "scene {s}: {r:?} against {want:?}");
        assert!(!same(&want, &measure(s, 1 - s)), "scene {s}: the scenes' videos score alike");
        let (index, name, camera, truth) = &seen.tracks[s];
        let video = velox::data::rgbd::read_scene_video(&dirs[s]).unwrap();
        assert_eq!((*index, name.as_str(), *camera), (s, names[s], video.camera));
        assert_eq!(truth, &track_scenes.load_with_visibility(s).unwrap().0.tracks);
    }
}

/// A tiny image-to-4D generator with random weights beside the fixture's autoencoder, as the
/// commands load them.
fn generator_models(gpu: &Gpu, ae: &Path) -> GeneratorModels {
    let cfg = GeneratorConfig {
        task: velox::models::config::GenerationTask::Image,
        tokens: 32,
        token_dim: 8,
        token_mean: vec![0.0; 8],
        token_std: vec![1.0; 8],
        ..GeneratorConfig::tiny()
    };
    let generator = Generator::new(gpu, &cfg, 2).unwrap();
    randomize_params(&generator.store, 8, 0.5);
    GeneratorModels { generator, ae: Autoencoder::load(gpu, ae).unwrap(), dino: None }
}

fn spec() -> GenerateSpec {
    GenerateSpec { steps: 2, sampler: Sampler::Euler, guidance: 1.0, seed: SEED, precision: Precision::F32 }
}

/// `eval generation` scene by scene, 2 novel views of 25, frames 0, 7 and 14: each scene's
/// scores are its own tokens' renders (the generator's from its own condition, the encoder's
/// stored ones) against its own video frame and its own supervision views, picked here
/// frame-major at 25 views a frame, and the kept frame's truths are its own. Would catch: the
/// novel views indexed with the number of views evaluated instead of the scene's (`f * views +
/// v`), the video's frames shifted, a scene scored against another's images or with another's
/// tokens.
#[test]
fn generation_measures_each_scene_against_its_own_views() {
    let gpu = gpu();
    let fx = fixture();
    let dirs = scene_dirs(fx);
    let models = generator_models(&gpu, &fx.ae);
    let scenes = TokenScenes::open(&gpu, &fx.data, None, Some(&fx.ae)).unwrap();
    let options = GenerationOptions {
        spec: spec(),
        source: VoxelSource::Input,
        voxel_decoder: None,
        sampling: Sampling::heun(64),
        frames: vec![0, 7, 14],
        views: 2,
        kept: vec![7],
    };
    let mut seen = Seen::default();
    let got = velox::tasks::evaluate::generation(&gpu, &models, &scenes, 2, &options, &mut seen).unwrap();
    let ae = &models.ae;
    let token_dir = fx.data.join("tokens");
    for (s, dir) in dirs.iter().enumerate() {
        let name = format!("scene_{s:05}");
        let scene = read_scene(dir, true).unwrap();
        let cloud = cloud_of(dir);
        let per_frame = scene.meta.supervision_views;
        let cams: Vec<Camera> = std::iter::once(scene.cameras.video.unwrap())
            .chain(scene.cameras.supervision[..2].iter().copied())
            .collect();
        let truth = |f: usize, v: usize| {
            if v == 0 {
                rgb(&scene.video[f])
            } else {
                rgb(&scene.supervision[f * per_frame + v - 1])
            }
        };
        let (made, _) = velox::tasks::evaluate::token_pair(&gpu, &models, &scenes, s, &options.spec).unwrap();
        let stored = stored_tokens(&gpu, &token_dir, &name);
        let r = &got[s];
        assert_eq!(r.scene, name);
        for (tokens, scores) in [(&made, r.generated), (&stored, r.encoded)] {
            let (mut input, mut novel) = ((Vec::new(), Vec::new()), (Vec::new(), Vec::new()));
            for &f in &options.frames {
                let points = points_of_frame(&cloud, f);
                for (v, cam) in cams.iter().enumerate() {
                    let img = render_frame(ae, tokens, &points, f, cam);
                    let into = if v == 0 { &mut input } else { &mut novel };
                    into.0.push(psnr(&img, &truth(f, v)));
                    into.1.push(ssim(&img, &truth(f, v), 16, 16, 3));
                }
            }
            let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * b.abs();
            assert!(
                close(scores.input.psnr, mean(&input.0)) && close(scores.input.ssim, mean(&input.1)),
                "{name} input: {scores:?}"
            );
            assert!(
                close(scores.novel.psnr, mean(&novel.0)) && close(scores.novel.ssim, mean(&novel.1)),
                "{name} novel: {scores:?}"
            );
        }
        let (kept_name, frame, truths) = &seen.renders[s];
        assert_eq!((kept_name.as_str(), *frame), (name.as_str(), 7));
        for (v, t) in truths.iter().enumerate() {
            assert_eq!(t, &truth(7, v), "{name}: the kept frame's truth of view {v}");
        }
        // The views differ from the next ones, and the frames from the next frames.
        let (a, b, c) = (truth(7, 1), truth(7, 2), truth(8, 1));
        assert!(psnr(&a, &b) < 40.0 && psnr(&a, &c) < 60.0, "views or frames alike");
    }
}

/// `eval cloth` scene by scene against records made known: each scene's `cloth.json` holds as
/// its simulated centre of mass the one of its own encoder tokens' surface at each frame
/// (sampled here at that frame's time with the decodings' seed rule), so its encoded RMSE is 0
/// (f32 rounding of the record), and its generated heights are its own generated tokens'
/// surface's; the observer is handed every frame of both decodings, in order. A record one
/// frame late, or the other scene's, scores a clearly larger RMSE (checked). Would catch: the
/// decoded frames shifted against the simulated ones, the generated and encoded tokens
/// swapped, a scene scored against another's record or with another's tokens.
#[test]
fn cloth_measures_each_scene_against_its_own_record() {
    let gpu = gpu();
    let fx = fixture();
    let dirs = scene_dirs(fx);
    let models = generator_models(&gpu, &fx.ae);
    let scenes = TokenScenes::open(&gpu, &fx.data, None, Some(&fx.ae)).unwrap();
    let sampling = Sampling { points: 128, steps: 2, sampler: Sampler::Euler };
    let token_dir = fx.data.join("tokens");
    let ae = &models.ae;
    let centres = |tokens: &Tensor| -> Vec<[f64; 3]> {
        (0..FRAMES)
            .map(|f| centre_of_mass(&surface_of_frame(ae, tokens, f, &sampling, SEED)).unwrap())
            .collect()
    };
    let stored: Vec<Tensor> =
        (0..2).map(|s| stored_tokens(&gpu, &token_dir, &format!("scene_{s:05}"))).collect();
    let encoded: Vec<Vec<[f64; 3]>> = stored.iter().map(centres).collect();
    for (s, dir) in dirs.iter().enumerate() {
        let record = ClothRecord {
            kind: GarmentKind::Towel,
            particles: 0,
            folds: 1,
            drop_height: 0.3,
            gravity: 19.62,
            ground: -0.5,
            up: up(),
            frame_seconds: 0.01,
            centre_of_mass: encoded[s].iter().map(|c| c.map(|v| v as f32)).collect(),
        };
        std::fs::write(dir.join("cloth.json"), serde_json::to_string(&record).unwrap()).unwrap();
    }
    let mut seen = Seen::default();
    let got =
        velox::tasks::evaluate::cloth(&gpu, &models, &scenes, 2, &spec(), &sampling, &mut seen).unwrap();
    let up64 = up().map(|v| v as f64);
    let h = |c: &[[f64; 3]]| heights(c, up64).unwrap();
    let rounded =
        |c: &[[f64; 3]]| -> Vec<[f64; 3]> { c.iter().map(|p| p.map(|v| v as f32 as f64)).collect() };
    for s in 0..2 {
        let r = &got[s].scene;
        assert_eq!(r.scene, format!("scene_{s:05}"));
        assert_eq!(got[s].frame_seconds, 0.01f32 as f64);
        let simulated = h(&rounded(&encoded[s]));
        assert_eq!(r.simulated, simulated, "scene {s}: the record's heights");
        assert!(r.rmse_encoded < 1e-6, "scene {s}: the encoder's own surface scores RMSE {}", r.rmse_encoded);
        let late: Vec<f64> = (0..FRAMES).map(|f| r.encoded[f.saturating_sub(1)]).collect();
        let (shifted, other) =
            (rmse(&late, &simulated).unwrap(), rmse(&h(&encoded[1 - s]), &simulated).unwrap());
        if verbose() {
            eprintln!(
                "cloth scene {s}: RMSE {:.1e}; a frame late {shifted:.2e}; the other scene's {other:.2e}",
                r.rmse_encoded
            );
        }
        assert!(shifted > 100.0 * r.rmse_encoded.max(1e-7) && other > 100.0 * r.rmse_encoded.max(1e-7));
        let (made, _) = velox::tasks::evaluate::token_pair(&gpu, &models, &scenes, s, &spec()).unwrap();
        let want = h(&centres(&made));
        assert!(
            r.generated.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-12),
            "scene {s}: generated heights"
        );
        // Every frame of both decodings, in order, each the frame's own surface.
        let handed = &seen.surfaces[2 * FRAMES * s..2 * FRAMES * (s + 1)];
        for (k, (which, f, c)) in handed.iter().enumerate() {
            let want_which = if k < FRAMES { ClothTokens::Generated } else { ClothTokens::Encoded };
            assert_eq!((*which, *f), (want_which, k % FRAMES));
            if *which == ClothTokens::Encoded {
                assert_eq!(c, &encoded[s][*f], "scene {s} frame {f}: the surface handed over");
            }
        }
    }
    for dir in &dirs {
        std::fs::remove_file(dir.join("cloth.json")).unwrap();
    }
}
