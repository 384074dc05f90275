//! The token store end to end: `velox_tasks::encode::encode_dataset` over a dataset of two tiny
//! scenes with a tiny autoencoder stores the encoder's tokens bit for bit with their query
//! points and the dataset's statistics; a re-run keeps what is stored, refuses tokens of
//! another origin without `force`; a changed checkpoint is refused; and `TokenScenes` gives
//! each scene its tokens and occupancy.

use crate::common;
use common::*;
use velox_models::Model;

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use velox::data::format::{read_ply, write_scene};
use velox::data::{procedural, read_scene, SynthOptions};
use velox::engine::Precision;
use velox::io::cloud;
use velox::models::config::AutoencoderConfig;
use velox::models::train::source::SampleSource;
use velox::models::velox::autoencoder::Autoencoder;
use velox::models::velox::tokens::{
    check_checkpoint, checkpoint_hash, read_scene_file, scene_file, CheckpointCheck, CloudSource,
    TokenFolder, TokenManifest, TokenStats, MANIFEST,
};
use velox::tasks::encode::{encode_dataset, EncodeOptions, EncodeReport};
use velox::tasks::TokenScenes;

const SCENES: [&str; 2] = ["scene_00000", "scene_00001"];

/// The tiny config with a time scale other than 1, so raw tau and the encoder's scaled tau
/// differ.
fn config() -> AutoencoderConfig {
    let mut c = AutoencoderConfig::tiny();
    c.encoder.time_scale = 2.5;
    c
}

/// Two procedural scenes (16 px, 2000 points) in `BASE/data` and a tiny untrained autoencoder
/// in `BASE/ae.safetensors`, made once; each test copies them.
fn base() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("velox-tokens-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let gpu = gpu();
        for (seed, name) in [3, 8].into_iter().zip(SCENES) {
            let (_, mesh) = procedural::scene(seed, None).unwrap();
            let opts =
                SynthOptions { res: 16, points: 2000, supersample: 1, tracks: 4, ..Default::default() };
            write_scene(&gpu, &mesh, "test", None, seed, &opts, &dir.join("data").join(name), &mut |_| {})
                .unwrap();
        }
        Autoencoder::new(&gpu, &config(), 1).unwrap().save(&dir.join("ae.safetensors")).unwrap();
        dir
    })
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// A fresh copy of the base in a folder of the test's own.
fn workspace(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("velox-tokens-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    copy_dir(base(), &dir);
    dir
}

fn options(dir: &Path, seed: u64) -> EncodeOptions {
    EncodeOptions {
        checkpoint: dir.join("ae.safetensors"),
        data: dir.join("data"),
        out: None,
        seed,
        precision: Precision::F32,
        force: false,
        source: CloudSource::Points,
        video_points: velox::data::rgbd::DEFAULT_POINTS,
    }
}

fn encode(options: &EncodeOptions) -> EncodeReport {
    encode_dataset(&gpu(), options, &mut ()).unwrap()
}

fn encode_err(options: &EncodeOptions) -> String {
    encode_dataset(&gpu(), options, &mut ()).unwrap_err().to_string()
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Every file of a folder by name, with its bytes.
fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .map(|p| (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read(&p).unwrap()))
        .collect();
    out.sort();
    out
}

#[test]
fn encoding_stores_the_encoders_tokens_bit_for_bit_with_the_datasets_statistics() {
    let gpu = gpu();
    let dir = workspace("bits");
    let opts = options(&dir, 7);
    let report = encode(&opts);
    let tokens_dir = dir.join("data/tokens");
    assert_eq!(report.dir, tokens_dir);
    assert_eq!((report.encoded.as_slice(), report.kept.len()), (&SCENES.map(String::from)[..], 0));
    assert!(report.replaced.is_none());

    let ckpt = std::fs::canonicalize(dir.join("ae.safetensors")).unwrap();
    let ae = Autoencoder::load(&gpu, &ckpt).unwrap();
    let manifest = TokenManifest::read(&tokens_dir).unwrap();
    assert_eq!(manifest, report.manifest);
    assert_eq!((manifest.tokens, manifest.token_dim, manifest.scenes.len()), (32, 8, 2));
    assert_eq!(manifest.origin.checkpoint, ckpt);
    assert_eq!(manifest.origin.checkpoint_hash, checkpoint_hash(&ckpt).unwrap());
    assert_eq!((manifest.origin.config.clone(), manifest.origin.seed), (config(), 7));
    let mut all_tokens = Vec::new();
    for name in SCENES {
        let (origin, stored) = read_scene_file(&scene_file(&tokens_dir, name)).unwrap();
        assert_eq!(origin, manifest.origin);
        assert_eq!(stored.scene, name);
        // The tokens `Autoencoder::encode` gives for that cloud and seed, bit for bit.
        let host: Vec<f32> = read_ply(&dir.join("data").join(name).join("points.ply")).unwrap().concat();
        let cloud_t = cloud::upload(&gpu, &host).unwrap();
        let expected: Vec<f32> = ae.encode(&cloud_t, 7).unwrap().read().unwrap();
        assert_eq!(bits(&stored.tokens), bits(&expected), "{name}: tokens");
        // The query points: the encoder layout's, with raw tau.
        let mut rec = gpu.recorder().unwrap();
        let (_, layout) = ae.encoder.layout(&mut rec, &cloud_t, &mut Rng::new(7)).unwrap();
        rec.submit().unwrap();
        let layout_points: Vec<f32> = layout.query_points.read().unwrap();
        let scaled: Vec<f32> =
            stored.query_points.chunks(4).flat_map(|p| [p[0], p[1], p[2], p[3] * 2.5]).collect();
        assert_eq!(bits(&scaled), bits(&layout_points), "{name}: query points");
        assert!(
            stored.query_points.chunks(4).any(|p| p[3] > 0.0)
                && stored.query_points.chunks(4).all(|p| p[3] <= 0.23)
        );
        all_tokens.extend(stored.tokens);
    }
    // The statistics against a plain two-pass computation over every token.
    let d = manifest.token_dim;
    let n = (all_tokens.len() / d) as f64;
    for c in 0..d {
        let col = all_tokens.chunks(d).map(|r| r[c] as f64);
        let mean = col.clone().sum::<f64>() / n;
        let std = (col.map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
        assert!((manifest.mean[c] - mean).abs() <= 1e-12 * mean.abs().max(std), "channel {c} mean");
        assert!((manifest.std[c] - std).abs() <= 1e-12 * std, "channel {c} std");
        assert!(std > 0.0);
    }
    // The same seed again, elsewhere: the same bytes, manifest included.
    let again = dir.join("again");
    encode(&EncodeOptions { out: Some(again.clone()), ..opts.clone() });
    assert_eq!(files(&again), files(&tokens_dir));
    // Another seed draws other queries, hence other tokens.
    let other = dir.join("other");
    encode(&EncodeOptions { out: Some(other.clone()), seed: 8, ..opts });
    let (_, a) = read_scene_file(&scene_file(&tokens_dir, SCENES[0])).unwrap();
    let (_, b) = read_scene_file(&scene_file(&other, SCENES[0])).unwrap();
    assert_ne!(bits(&a.tokens), bits(&b.tokens));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_rerun_keeps_what_is_stored_and_refuses_tokens_of_another_origin_without_force() {
    let dir = workspace("rerun");
    let opts = options(&dir, 7);
    let tokens_dir = dir.join("data/tokens");
    let first = encode(&opts);
    let stored = files(&tokens_dir);
    // Everything is stored: nothing is encoded, nothing changes.
    let second = encode(&opts);
    assert_eq!((second.encoded.len(), second.kept.len()), (0, 2));
    assert_eq!(files(&tokens_dir), stored);
    // One scene's file gone (an interrupted run): only it is encoded, to the same bytes.
    std::fs::remove_file(scene_file(&tokens_dir, SCENES[1])).unwrap();
    let third = encode(&opts);
    assert_eq!(
        (third.encoded.as_slice(), third.kept.as_slice()),
        (&[SCENES[1].to_string()][..], &[SCENES[0].to_string()][..])
    );
    assert_eq!(files(&tokens_dir), stored);
    assert_eq!(third.manifest, first.manifest);
    // --force encodes every scene again.
    assert_eq!(encode(&EncodeOptions { force: true, ..opts.clone() }).encoded.len(), 2);
    assert_eq!(files(&tokens_dir), stored);

    // Another seed or precision over these tokens: refused, unless forced.
    let e = encode_err(&EncodeOptions { seed: 8, ..opts.clone() });
    assert!(e.contains("seed 7, not 8") && e.contains("`force`") && e.contains("tokens"), "{e}");
    let e = encode_err(&EncodeOptions { precision: Precision::F16, ..opts.clone() });
    assert!(e.contains("precision f32, not f16"), "{e}");
    // A scene file of another seed without a manifest (a forced run that stopped): refused.
    std::fs::remove_file(tokens_dir.join(MANIFEST)).unwrap();
    let other = dir.join("seed8");
    encode(&EncodeOptions { out: Some(other.clone()), seed: 8, ..opts.clone() });
    std::fs::copy(scene_file(&other, SCENES[0]), scene_file(&tokens_dir, SCENES[0])).unwrap();
    let e = encode_err(&opts);
    assert!(e.contains("scene_00000.safetensors") && e.contains("seed 8, not 7"), "{e}");
    // An unreadable scene file: refused, naming it.
    std::fs::write(scene_file(&tokens_dir, SCENES[0]), b"not tokens").unwrap();
    let e = encode_err(&opts);
    assert!(e.contains("scene_00000.safetensors") && e.contains("remove it"), "{e}");
    let forced = encode(&EncodeOptions { force: true, ..opts.clone() });
    assert_eq!(forced.encoded.len(), 2);
    assert_eq!(files(&tokens_dir), stored);

    // A checkpoint trained further (here: another one written over it) is refused by every
    // reader and by a re-run without --force.
    let ckpt = dir.join("ae.safetensors");
    Autoencoder::new(&gpu(), &config(), 2).unwrap().save(&ckpt).unwrap();
    for given in [None, Some(ckpt.as_path())] {
        let e = TokenFolder::open(&tokens_dir, given).unwrap_err().to_string();
        assert!(e.contains("encoder changed") && e.contains("velox encode"), "{e}");
    }
    let e = TokenScenes::open(&gpu(), &dir.join("data"), None, None).err().unwrap().to_string();
    assert!(e.contains("encoder changed"), "{e}");
    let e = encode_err(&opts);
    assert!(e.contains("not ") && e.contains("hash") && e.contains("`force`"), "{e}");
    let replaced = encode(&EncodeOptions { force: true, ..opts.clone() });
    assert!(replaced.replaced.as_deref().is_some_and(|r| r.contains(&first.manifest.origin.checkpoint_hash)));
    assert_ne!(replaced.manifest.origin.checkpoint_hash, first.manifest.origin.checkpoint_hash);
    // The checkpoint gone: accepted with a note when none is named, refused against another.
    std::fs::rename(&ckpt, dir.join("moved.safetensors")).unwrap();
    let folder = TokenFolder::open(&tokens_dir, None).unwrap();
    assert!(folder.checkpoint.note().is_some_and(|n| n.contains("is gone")), "{:?}", folder.checkpoint);
    let moved = dir.join("moved.safetensors");
    assert_eq!(
        check_checkpoint(&tokens_dir, &folder.manifest, Some(&moved)).unwrap(),
        CheckpointCheck::Verified(moved)
    );
    let another = dir.join("another.safetensors");
    Autoencoder::new(&gpu(), &config(), 3).unwrap().save(&another).unwrap();
    let e = check_checkpoint(&tokens_dir, &folder.manifest, Some(&another)).unwrap_err().to_string();
    assert!(e.contains("another.safetensors") && e.contains("encoder changed"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn token_scenes_give_each_scene_its_tokens_and_occupancy() {
    let gpu = gpu();
    let dir = workspace("source");
    let data = dir.join("data");
    let ckpt = dir.join("ae.safetensors");
    encode(&options(&dir, 0));
    let scenes = TokenScenes::open(&gpu, &data, None, Some(&ckpt)).unwrap();
    assert_eq!(scenes.names(), SCENES);
    assert!(matches!(scenes.checkpoint(), CheckpointCheck::Verified(_)));
    assert_eq!(scenes.manifest().scenes, SCENES);
    for (i, name) in SCENES.iter().enumerate() {
        let sample = scenes.load(i).unwrap();
        let truth = read_scene(&data.join(name), false).unwrap();
        assert_eq!(sample.occupancy, truth.occupancy, "{name}");
        assert_eq!(sample.frames(), 24);
        assert!(sample.occupancy.iter().any(|&w| w != 0));
        let (_, stored) = read_scene_file(&scene_file(&data.join("tokens"), name)).unwrap();
        assert_eq!(sample.tokens.shape(), [32, 8]);
        assert_eq!(bits(&sample.tokens.read::<f32>().unwrap()), bits(&stored.tokens));
    }
    // Statistics of a scene's tokens alone are not the dataset's.
    let (_, one) = read_scene_file(&scene_file(&data.join("tokens"), SCENES[0])).unwrap();
    assert_ne!(TokenStats::of(&one.tokens, 8).mean(), scenes.manifest().mean.as_slice());

    // A scene the tokens lack, then a scene the dataset lacks: refused by name.
    copy_dir(&data.join(SCENES[1]), &data.join("scene_00002"));
    let e = TokenScenes::open(&gpu, &data, None, None).err().unwrap().to_string();
    assert!(e.contains("lacks 1 scene(s)") && e.contains("scene_00002") && e.contains("velox encode"), "{e}");
    let report = encode(&options(&dir, 0));
    assert_eq!(report.encoded, ["scene_00002"]);
    assert_eq!(TokenScenes::open(&gpu, &data, None, None).unwrap().len(), 3);
    std::fs::remove_dir_all(data.join(SCENES[0])).unwrap();
    let e = TokenScenes::open(&gpu, &data, None, None).err().unwrap().to_string();
    assert!(e.contains("lists 1 scene(s)") && e.contains(SCENES[0]), "{e}");
    // A scene file gone, or damaged: named.
    encode(&options(&dir, 0));
    let file = scene_file(&data.join("tokens"), SCENES[1]);
    let bytes = std::fs::read(&file).unwrap();
    std::fs::remove_file(&file).unwrap();
    let e = TokenScenes::open(&gpu, &data, None, None).err().unwrap().to_string();
    assert!(e.contains("scene_00001.safetensors") && e.contains("missing"), "{e}");
    let mut nan = bytes.clone();
    let at = nan.len() - 4;
    nan[at..].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&file, &nan).unwrap();
    let scenes = TokenScenes::open(&gpu, &data, None, None).unwrap();
    let e = scenes.load(0).err().unwrap().to_string();
    assert!(e.contains("scene_00001.safetensors") && e.contains("NaN"), "{e}");
    // Tokens in a folder of their own, named.
    let elsewhere = dir.join("elsewhere");
    std::fs::rename(data.join("tokens"), &elsewhere).unwrap();
    assert!(TokenScenes::open(&gpu, &data, None, None).is_err());
    std::fs::write(scene_file(&elsewhere, SCENES[1]), &bytes).unwrap();
    assert_eq!(TokenScenes::open(&gpu, &data, Some(&elsewhere), None).unwrap().len(), 2);
    let _ = std::fs::remove_dir_all(&dir);
}
