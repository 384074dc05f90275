//! The tiny autoencoder on one synthetic scene: it overfits (geometry and image losses fall
//! well below their start), a resumed run continues exactly like an uninterrupted one, and bad
//! scenes get clear errors.

mod common;
use common::*;
use velox::data::format::write_scene;
use velox::data::training::train_scene;
use velox::data::{procedural, read_scene, SynthOptions};
use velox::models::config::AutoencoderConfig;
use velox::models::velox::autoencoder::{Autoencoder, StepLosses, TrainScene};

fn scene(gpu: &Gpu, name: &str) -> TrainScene {
    let dir = std::env::temp_dir().join(format!("velox-ae-{}-{name}", std::process::id()));
    let (_, mesh) = procedural::scene(3, None).unwrap();
    let opts = SynthOptions { res: 32, points: 4000, supersample: 1, tracks: 8 };
    write_scene(gpu, &mesh, "test", None, 3, &opts, &dir, &mut |_| {}).unwrap();
    let s = read_scene(&dir, true).unwrap();
    let t = train_scene(gpu, &s).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    t
}

fn mean(l: &[StepLosses], f: impl Fn(&StepLosses) -> f64) -> f64 {
    l.iter().map(f).sum::<f64>() / l.len() as f64
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
fn a_resumed_run_continues_like_an_uninterrupted_one() {
    let gpu = gpu();
    let data = scene(&gpu, "resume");
    let cfg = AutoencoderConfig::tiny();
    let run = |ae: &mut Autoencoder, steps: std::ops::RangeInclusive<u64>| {
        for s in steps {
            ae.train_step(&data, s, &mut Autoencoder::step_rng(7, s)).unwrap();
        }
    };
    let mut whole = Autoencoder::new(&gpu, &cfg, 1).unwrap();
    run(&mut whole, 1..=4);
    let mut first = Autoencoder::new(&gpu, &cfg, 1).unwrap();
    run(&mut first, 1..=2);
    let path = std::env::temp_dir().join(format!("velox-ae-resume-{}.safetensors", std::process::id()));
    first.save(&path).unwrap();
    let mut resumed = Autoencoder::load(&gpu, &path).unwrap();
    std::fs::remove_file(&path).ok();
    assert_eq!(resumed.store.step(), 2);
    assert_eq!(resumed.cfg, cfg);
    run(&mut resumed, 3..=4);
    let a: Vec<f32> = whole.store.flat_params().read().unwrap();
    let b: Vec<f32> = resumed.store.flat_params().read().unwrap();
    // Atomic additions in the rasteriser's backward pass may sum in another order, so the
    // two runs agree to rounding rather than bit for bit.
    assert_nmse("resumed parameters", &b, &f64s(&a), 1e-10);
    assert_eq!(whole.store.step(), resumed.store.step());
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
    assert!(TrainScene::new(&gpu, nan, vec![cam], vec![vec![0.0; 192]; 24]).is_err());
    let mut late = cloud;
    late[6] = 0.5;
    assert!(TrainScene::new(&gpu, late, vec![cam], vec![vec![0.0; 192]; 24])
        .err()
        .unwrap()
        .to_string()
        .contains("frame"));
    let path = std::env::temp_dir().join(format!("velox-ae-bad-{}.safetensors", std::process::id()));
    std::fs::write(&path, b"not a checkpoint").unwrap();
    let err = Autoencoder::load(&gpu, &path).err().unwrap().to_string();
    std::fs::remove_file(&path).ok();
    assert!(err.contains("corrupt"), "{err}");
}
