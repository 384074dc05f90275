//! The tiny autoencoder on one synthetic scene: its composed backward pass (encoder, surface
//! decoder, Gaussian decoder and rasteriser, wired by `Autoencoder::accumulate`) against
//! central differences of its loss, it overfits (geometry and image losses fall well below
//! their start), two runs with one seed and a resumed run write the same checkpoint bytes as
//! an uninterrupted one, the f16 path follows the f32 path, and bad scenes get clear errors.

use crate::common;
use common::*;
use velox::data::format::write_scene;
use velox::data::{procedural, read_scene, SynthOptions};
use velox::engine::ops::cast::reference::to_f16;
use velox::engine::Precision;
use velox::models::config::AutoencoderConfig;
use velox::models::run::RunSettings;
use velox::models::train::trainer::{run_settings, save_checkpoint};
use velox::models::velox::autoencoder::{tau_of, Autoencoder, StepLosses, TrainScene};
use velox::tasks::training::train_scene;
use velox_models::Model;

fn scene(gpu: &Gpu, name: &str) -> TrainScene {
    scene_of(gpu, name, 3)
}

/// Procedural scene `seed` at 32 x 32 with 4000 points.
fn scene_of(gpu: &Gpu, name: &str, seed: u64) -> TrainScene {
    let dir = std::env::temp_dir().join(format!("velox-ae-{}-{name}", std::process::id()));
    let (_, mesh) = procedural::scene(seed, None).unwrap();
    let opts = SynthOptions { res: 32, points: 4000, supersample: 1, tracks: 8, ..Default::default() };
    write_scene(gpu, &mesh, "test", None, 3, &opts, &dir, &mut |_| {}).unwrap();
    let s = read_scene(&dir, true).unwrap();
    let t = train_scene(gpu, &s).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    t
}

fn mean(l: &[StepLosses], f: impl Fn(&StepLosses) -> f64) -> f64 {
    l.iter().map(f).sum::<f64>() / l.len() as f64
}

/// The finite differences' steps and bound. The loss is read in f32 (about 1.2: rounding of
/// 1e-7), so the encoder, whose derivative is about 1e-3, takes a longer step. Measured on
/// lavapipe: every part within 1.3e-2 of the analytic derivative (the Gaussian decoder's, whose
/// image loss jumps where Gaussians cross the rasteriser's alpha threshold), the surface
/// decoder's within 1e-4, the encoder's within 8e-3. With the surface decoder's token gradient
/// overwriting the others' (its accumulate flag flipped) the encoder's is 26 % off.
const H: f32 = 1e-3;
const H_ENCODER: f32 = 4e-3;
const REL: f64 = 3e-2;
const ABS: f64 = 1e-5;

/// The whole step's gradient against central differences of the step's loss (the same draws
/// each time): along directions over every parameter, over each part alone (the encoder alone
/// is reached only through both decoders and the token loss, so it checks how their token
/// gradients are summed), and over each parameter tensor alone. The parameters are
/// randomised so that no layer's small start (adaLN-Zero maps, output layers) hides the
/// layers before it. Would catch: a decoder's token gradient overwriting the other's instead
/// of adding to it (the accumulate flag flipped), a frame's Gaussian gradients copied to the
/// wrong rows, a missing term, any op's backward wired to the wrong tensor.
#[test]
fn the_composed_backward_matches_central_differences() {
    let gpu = gpu();
    let data = scene(&gpu, "fd");
    // Two frames of two views each (the per-frame copies and the per-view sums), one Gaussian
    // per voxel: with several in a voxel at nearly one depth, their order in the blend swaps
    // every few 1e-4 along a direction and the loss jumps (by 1e-5 where it moves 1e-6 between
    // jumps), too often for a finite difference to see between them.
    let mut cfg = AutoencoderConfig { frames_per_sample: 2, views_per_step: 2, ..AutoencoderConfig::tiny() };
    cfg.gaussians.gaussians_per_voxel = 1;
    let mut ae = Autoencoder::new(&gpu, &cfg, 1).unwrap();
    randomize_params(&ae.store, 11, 0.6);
    let draws = || vec![Rng::new(31)];
    let mut rec = gpu.recorder().unwrap();
    ae.store.zero_grads(&mut rec).unwrap();
    rec.submit().unwrap();
    let l0 = ae.accumulate(&[&data], &mut draws(), 1.0).unwrap();
    assert!(l0.terms.iter().all(|t| t.1 > 0.0), "{l0:?}");
    let grads: Vec<f32> = ae.store.flat_grads().read().unwrap();
    let theta: Vec<f32> = ae.store.flat_params().read().unwrap();
    let parts = ["", "surface.", "gaussians."].map(|p| ParamGroup::under(&ae.store, p));
    let encoder = [ParamGroup::under(&ae.store, "encoder.")];
    let mut loss_at = |p: &[f32]| {
        ae.store.flat_params().write(p).unwrap();
        ae.accumulate(&[&data], &mut draws(), 1.0).unwrap().total()
    };
    let mut rng = Rng::new(5);
    let worst = check_directional(
        "autoencoder",
        &theta,
        &grads,
        &parts,
        (2, 3),
        H,
        (REL, ABS),
        &mut rng,
        &mut loss_at,
    );
    let worst_encoder = check_directional(
        "autoencoder",
        &theta,
        &grads,
        &encoder,
        (3, 3),
        H_ENCODER,
        (REL, ABS),
        &mut rng,
        &mut loss_at,
    );
    if verbose() {
        eprintln!("autoencoder: worst relative error {worst:.2e} (encoder alone {worst_encoder:.2e})");
    }
}

#[test]
fn tiny_autoencoder_overfits_one_scene() {
    let gpu = gpu();
    let data = scene(&gpu, "overfit");
    let mut ae = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 1).unwrap();
    let mut rng = Rng::new(2);
    let steps = 100;
    let losses: Vec<StepLosses> = (1..=steps).map(|s| ae.train_step(&data, s, &mut rng).unwrap()).collect();
    let (first, last) = (&losses[..10], &losses[losses.len() - 10..]);
    let (v0, v1) = (mean(first, |l| l.surface), mean(last, |l| l.surface));
    let (g0, g1) = (mean(first, |l| l.gaussians), mean(last, |l| l.gaussians));
    if std::env::var_os("VELOX_TEST_VERBOSE").is_some() {
        eprintln!("tiny autoencoder, {steps} steps: surface {v0:.4} -> {v1:.4}, image {g0:.5} -> {g1:.5}");
    }
    assert!(v1 < 0.5 * v0, "surface loss {v0} -> {v1}");
    assert!(g1 < 0.5 * g0, "image loss {g0} -> {g1}");
}

#[test]
fn several_views_per_step_and_an_encoder_subset_train() {
    // Every view of the frame each step (more than the scene has: clamped to all of them),
    // and the encoder on a fresh quarter of the cloud each step.
    let gpu = gpu();
    let data = scene(&gpu, "views");
    let mut cfg = AutoencoderConfig::tiny();
    cfg.views_per_step = 1000;
    cfg.encoder_points = 1000;
    let mut ae = Autoencoder::new(&gpu, &cfg, 1).unwrap();
    let mut rng = Rng::new(2);
    let losses: Vec<StepLosses> = (1..=40).map(|s| ae.train_step(&data, s, &mut rng).unwrap()).collect();
    let (g0, g1) = (mean(&losses[..5], |l| l.gaussians), mean(&losses[35..], |l| l.gaussians));
    if std::env::var_os("VELOX_TEST_VERBOSE").is_some() {
        eprintln!("all views per step, 1000 encoder points, 40 steps: image {g0:.5} -> {g1:.5}");
    }
    assert!(g1 < 0.5 * g0, "image loss {g0} -> {g1}");
    cfg.views_per_step = 0;
    assert!(cfg.validate().unwrap_err().to_string().contains("views_per_step"));
}

#[test]
fn a_batch_gives_the_mean_of_its_samples_gradients() {
    // Four samples (two scenes, each twice with other draws), two frames and two views each:
    // one micro-batch of four against four micro-batches of one, each weighted 1/4.
    let gpu = gpu();
    let scenes = [scene_of(&gpu, "batch-a", 3), scene_of(&gpu, "batch-b", 8)];
    let cfg = AutoencoderConfig { frames_per_sample: 2, views_per_step: 2, ..AutoencoderConfig::tiny() };
    let mut ae = Autoencoder::new(&gpu, &cfg, 1).unwrap();
    let samples = [&scenes[0], &scenes[1], &scenes[0], &scenes[1]];
    let rngs = || (0..4).map(|i| Rng::new(70 + i)).collect::<Vec<_>>();
    let zero = |ae: &Autoencoder| {
        let mut rec = gpu.recorder().unwrap();
        ae.store.zero_grads(&mut rec).unwrap();
        rec.submit().unwrap();
    };
    zero(&ae);
    let batch = ae.accumulate(&samples, &mut rngs(), 0.25).unwrap();
    let batch_grads: Vec<f32> = ae.store.flat_grads().read().unwrap();
    zero(&ae);
    let mut singles = velox::models::train::Losses::default();
    for (s, mut r) in samples.iter().zip(rngs()) {
        singles.add(&ae.accumulate(&[s], std::slice::from_mut(&mut r), 0.25).unwrap());
    }
    let single_grads: Vec<f32> = ae.store.flat_grads().read().unwrap();
    assert!(batch_grads.iter().any(|&g| g != 0.0));
    assert_nmse("batch-4 gradient against four batch-1 gradients", &batch_grads, &f64s(&single_grads), 1e-10);
    for ((name, a), (_, b)) in batch.terms.iter().zip(&singles.terms) {
        assert!((a - b).abs() <= 1e-6 * b.abs().max(1e-12), "{name}: batch {a} against singles {b}");
    }
}

#[test]
fn runs_repeat_and_resume_bit_for_bit() {
    let gpu = gpu();
    let data = scene(&gpu, "resume");
    // Every supervision view each step: many tiles, so racing adds would show.
    let cfg = AutoencoderConfig { views_per_step: 25, ..AutoencoderConfig::tiny() };
    let run = |ae: &mut Autoencoder, steps: std::ops::RangeInclusive<u64>| {
        for s in steps {
            ae.train_step(&data, s, &mut Autoencoder::step_rng(7, s)).unwrap();
        }
    };
    let dir = std::env::temp_dir().join(format!("velox-ae-repeat-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let saved = |ae: &Autoencoder, name: &str| -> Vec<u8> {
        let path = dir.join(name);
        ae.save(&path).unwrap();
        std::fs::read(&path).unwrap()
    };
    // Two runs with the same seed write the same checkpoint, byte for byte.
    let mut whole = Autoencoder::new(&gpu, &cfg, 1).unwrap();
    run(&mut whole, 1..=4);
    let mut again = Autoencoder::new(&gpu, &cfg, 1).unwrap();
    run(&mut again, 1..=4);
    let whole_bytes = saved(&whole, "whole.safetensors");
    assert!(whole_bytes == saved(&again, "again.safetensors"), "two runs with the same seed differ");
    // A run stopped at step 2 and resumed from its checkpoint ends with the same bytes.
    let mut first = Autoencoder::new(&gpu, &cfg, 1).unwrap();
    run(&mut first, 1..=2);
    let path = dir.join("first.safetensors");
    first.save(&path).unwrap();
    assert_eq!(run_settings(&path).unwrap(), None, "saved outside a run");
    // A training run's settings travel with the checkpoint.
    let settings = RunSettings {
        seed: 7,
        steps: 4,
        steps_per_scene: 2,
        cooldown: 1,
        global_batch: 1,
        accumulate: 1,
        scenes: vec!["scene_00000".into()],
        precision: velox::engine::Precision::F16,
    };
    save_checkpoint(&first, &settings, &path).unwrap();
    assert_eq!(run_settings(&path).unwrap(), Some(settings));
    assert_eq!(Autoencoder::checkpoint_config(&path).unwrap(), cfg);
    let mut resumed = Autoencoder::load(&gpu, &path).unwrap();
    assert_eq!(resumed.store.step(), 2);
    assert_eq!(resumed.cfg, cfg);
    run(&mut resumed, 3..=4);
    assert!(whole_bytes == saved(&resumed, "resumed.safetensors"), "the resumed run differs");
    std::fs::remove_dir_all(&dir).ok();
    let b: Vec<f32> = resumed.store.flat_params().read().unwrap();

    // The learning-rate factor (`velox train --cooldown`) reaches the update: at 0 a step
    // leaves every parameter as it was, and the step reports the scaled rate.
    resumed.lr_scale = 0.0;
    let l = resumed.train_step(&data, 5, &mut Autoencoder::step_rng(7, 5)).unwrap();
    assert_eq!(l.lr, 0.0);
    assert_eq!(resumed.store.flat_params().read::<f32>().unwrap(), b, "lr 0 moved the parameters");
}

#[test]
fn the_f16_path_follows_the_f32_path() {
    let gpu = gpu();
    let data = scene(&gpu, "f16");
    let mut ae = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 3).unwrap();
    let mut rng = Rng::new(4);
    for s in 1..=5 {
        ae.train_step(&data, s, &mut rng).unwrap();
    }
    let frame = data.frames()[0];
    let tau = tau_of(frame);
    let centres = ae.voxels_from_points(&data.frame_points[frame], tau);
    let spec = Autoencoder::default_sampling(200, 5);
    let spec = velox::models::velox::surface::SampleSpec { steps: 4, ..spec };
    // (tokens, Gaussian outputs, surface points) in the autoencoder's precision; the decoders
    // read the f32 tokens in both runs, so each error is the decoder's own.
    let run = |ae: &Autoencoder, tokens: Option<&Tensor>| {
        let own = ae.encode(&data.cloud, 9).unwrap();
        let tokens = tokens.unwrap_or(&own);
        let g = ae.decode_gaussians(tokens, &centres, tau).unwrap();
        let mut head = Vec::new();
        for t in [&g.means, &g.log_scales, &g.quats, &g.opacities, &g.colours] {
            head.extend(t.read::<f32>().unwrap());
        }
        let points: Vec<f32> = ae.decode_points(tokens, tau, &spec).unwrap().read().unwrap();
        (own, head, points)
    };
    let (tokens, head32, points32) = run(&ae, None);
    ae.set_precision(Precision::F16).unwrap();
    // The f16 copies hold the trained parameters, rounded.
    let (name, p, _) = ae.store.iter().find(|(n, _, _)| n.contains("encoder")).unwrap();
    let half: Vec<f64> =
        ae.store.param_half(name).unwrap().read::<half::f16>().unwrap().iter().map(|h| h.to_f64()).collect();
    assert_eq!(half, to_f16(&p.read::<f32>().unwrap()), "f16 copy of {name}");
    let (tokens16, head16, points16) = run(&ae, Some(&tokens));
    let tokens32: Vec<f32> = tokens.read().unwrap();
    // Measured on lavapipe: tokens 1.7e-7, Gaussians 1.5e-10, points 1.1e-10 (the decoders
    // after five steps are still close to their adaLN-Zero start, so their errors are small).
    let tokens16: Vec<f32> = tokens16.read().unwrap();
    eprintln!(
        "f16 against f32 ({}): tokens {:.2e}, Gaussians {:.2e}, points {:.2e}",
        velox::engine::ops::matmul::matmul_variant(&gpu, velox::engine::DType::F16),
        nmse(&tokens16, &f64s(&tokens32)),
        nmse(&head16, &f64s(&head32)),
        nmse(&points16, &f64s(&points32))
    );
    assert_nmse("f16 tokens", &tokens16, &f64s(&tokens32), 2e-5);
    assert_nmse("f16 Gaussian decoder", &head16, &f64s(&head32), 2e-8);
    assert_nmse("f16 surface points", &points16, &f64s(&points32), 1e-8);
    assert_ne!(head16, head32, "the f16 path ran in f32");
}

#[test]
fn bad_scenes_and_checkpoints_get_clear_errors() {
    let gpu = gpu();
    let cam = velox::engine::ops::raster::Camera::identity(40.0, 8, 8);
    let cloud = vec![0.1f32, 0.2, 0.3, 0.5, 0.5, 0.5, 0.0];
    let err = TrainScene::new(&gpu, cloud.clone(), vec![cam], vec![vec![0.0; 192]; 3]).err().unwrap();
    assert!(err.to_string().contains("24 x 1 supervision images"), "{err}");
    let err = TrainScene::new(&gpu, cloud.clone(), vec![cam], vec![vec![0.0; 10]; 24]).err().unwrap();
    assert!(err.to_string().contains("size"), "{err}");
    let mut nan = cloud.clone();
    nan[0] = f32::NAN;
    let err = TrainScene::new(&gpu, nan, vec![cam], vec![vec![0.0; 192]; 24]).err().unwrap().to_string();
    assert!(err.contains("point 0 has a non-finite value in channel 0"), "{err}");
    let mut late = cloud;
    late[6] = 0.5;
    assert!(TrainScene::new(&gpu, late, vec![cam], vec![vec![0.0; 192]; 24])
        .err()
        .unwrap()
        .to_string()
        .contains("frame"));
    let path = std::env::temp_dir().join(format!("velox-ae-bad-{}.safetensors", std::process::id()));
    std::fs::write(&path, b"not a checkpoint").unwrap();
    let loaded = Autoencoder::load(&gpu, &path).map(|_| ());
    std::fs::remove_file(&path).ok();
    file_error(loaded, &path, velox::engine::FileOp::Content);
}
