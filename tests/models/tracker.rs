//! The tracking network at the tiny config: its backward pass against finite differences per
//! tensor (L1 and L2), a batch against its samples alone, that it learns a motion beyond the
//! static baseline, that each scene is tracked from its own tokens, that queries are tracked
//! independently of each other, the occlusion test, and the paper config's parameter count.

use crate::common;
use common::*;
use velox::models::config::{TrackLoss, TrackerConfig};
use velox::models::train::Trainable;
use velox::models::velox::tracker::{Track, TrackSample, Tracker};

/// Tracks of `n` random queries under a smooth motion: a drift and a shear growing with time
/// (`sign` -1 runs it the other way).
fn tracks(seed: u64, n: usize, sign: f32) -> Vec<Track> {
    let mut rng = Rng::new(seed);
    (0..n)
        .map(|_| {
            let q = [0; 3].map(|_| rng.range(-0.8, 0.8) as f32);
            std::array::from_fn(|f| {
                let s = sign * f as f32 / 23.0;
                [q[0] + 0.2 * s, q[1] + 0.3 * s * q[0], q[2] - 0.1 * s * s.abs()]
            })
        })
        .collect()
}

fn sample(gpu: &Gpu, seed: u64, n: usize) -> TrackSample {
    scene(gpu, seed, seed, n, 1.0)
}

/// A sample whose tokens come from `token_seed` and whose tracks (queries from `seed`) move
/// forwards or backwards (`sign`); token points and colours from `seed`.
fn scene(gpu: &Gpu, seed: u64, token_seed: u64, n: usize, sign: f32) -> TrackSample {
    let mut rng = Rng::new(seed);
    // A sample's own tokens are the first draws of its seed (as before there were two).
    let tokens =
        if token_seed == seed { rng.normal_vec(48 * 32) } else { Rng::new(token_seed).normal_vec(48 * 32) };
    let points: Vec<f32> = (0..48)
        .flat_map(|i| {
            [0; 3].map(|_| rng.range(-1.0, 1.0) as f32).into_iter().chain([(i % 24) as f32 / 100.0])
        })
        .collect();
    let colours = (0..n).map(|_| [0; 3].map(|_| rng.uniform() as f32)).collect();
    TrackSample::new(
        Tensor::from_slice(gpu, &[48, 32], &tokens).unwrap(),
        Tensor::from_slice(gpu, &[48, 4], &points).unwrap(),
        tracks(seed, n, sign),
        colours,
    )
    .unwrap()
}

fn zero(gpu: &Gpu, t: &Tracker) {
    let mut rec = gpu.recorder().unwrap();
    t.store.zero_grads(&mut rec).unwrap();
    rec.submit().unwrap();
}

/// The step's gradient against central differences of its loss, along directions over every
/// parameter and over each tensor alone, with the parameters randomised: at the default start
/// the head's last layer (std 1e-3) shrinks every upstream gradient, so a wrong gradient in a
/// trunk tensor would hide under the head's. Would catch any tensor's gradient wired wrong,
/// the cross-attention's included.
#[test]
fn backward_matches_central_differences_per_tensor() {
    let gpu = gpu();
    for (loss, token_positions, query_colour) in
        [(TrackLoss::L2, false, false), (TrackLoss::L1, false, false), (TrackLoss::L2, true, true)]
    {
        let cfg = TrackerConfig {
            loss,
            token_positions,
            query_colour,
            queries_per_sample: 40,
            ..TrackerConfig::tiny()
        };
        let mut t = Tracker::new(&gpu, &cfg, 2).unwrap();
        randomize_params(&t.store, 12, 0.6);
        let s = sample(&gpu, 4, 60);
        zero(&gpu, &t);
        let l0 = t.accumulate(&[&s], &mut [Rng::new(9)], 1.0).unwrap();
        assert!(l0.total() > 0.0, "{l0:?}");
        let grad: Vec<f32> = t.store.flat_grads().read().unwrap();
        let theta: Vec<f32> = t.store.flat_params().read().unwrap();
        let mut groups = vec![ParamGroup::under(&t.store, "")];
        groups.extend(ParamGroup::each(&t.store));
        // L1 has a kink wherever a prediction meets its target: a small step crosses few.
        let (h, bounds) = match loss {
            TrackLoss::L2 => (1e-3f32, (1e-2, 1e-5)),
            TrackLoss::L1 => (1e-4f32, (2e-2, 1e-4)),
        };
        let what = format!("{loss:?}, token positions {token_positions}, colour {query_colour}");
        let mut at = |p: &[f32]| {
            t.store.flat_params().write(p).unwrap();
            t.accumulate(&[&s], &mut [Rng::new(9)], 1.0).unwrap().total()
        };
        let worst =
            check_directional(&what, &theta, &grad, &groups, (1, 1), h, bounds, &mut Rng::new(5), &mut at);
        if verbose() {
            eprintln!("{what}: worst relative error {worst:.2e}");
        }
    }
}

#[test]
fn a_batch_gives_the_mean_of_its_samples_gradients() {
    let gpu = gpu();
    let cfg = TrackerConfig { queries_per_sample: 30, ..TrackerConfig::tiny() };
    let mut t = Tracker::new(&gpu, &cfg, 1).unwrap();
    // Different numbers of tracks: the second scene has fewer than a sample draws.
    let samples = [sample(&gpu, 1, 50), sample(&gpu, 2, 20), sample(&gpu, 3, 35)];
    let refs: Vec<&TrackSample> = samples.iter().collect();
    let rngs = || (0..3).map(|i| Rng::new(20 + i)).collect::<Vec<_>>();
    zero(&gpu, &t);
    let batch = t.accumulate(&refs, &mut rngs(), 1.0 / 3.0).unwrap();
    let batch_grads: Vec<f32> = t.store.flat_grads().read().unwrap();
    zero(&gpu, &t);
    let mut total = 0.0;
    for (s, mut r) in refs.iter().zip(rngs()) {
        total += t.accumulate(&[s], std::slice::from_mut(&mut r), 1.0 / 3.0).unwrap().total();
    }
    let single_grads: Vec<f32> = t.store.flat_grads().read().unwrap();
    assert_nmse(
        "batch-3 gradient against three batch-1 gradients",
        &batch_grads,
        &f64s(&single_grads),
        1e-10,
    );
    assert!((batch.total() - total).abs() <= 1e-6 * total, "batch {} against singles {total}", batch.total());
}

#[test]
fn an_untrained_tracker_stays_put_and_a_trained_one_learns_the_motion() {
    let gpu = gpu();
    let cfg = TrackerConfig { queries_per_sample: 128, ..TrackerConfig::tiny() };
    let mut t = Tracker::new(&gpu, &cfg, 3).unwrap();
    let s = sample(&gpu, 6, 400);
    let queries: Vec<[f32; 3]> = s.tracks.iter().map(|t| t[0]).collect();
    // The head starts near zero: every frame predicts about the query (the static baseline).
    let before = t.predict(&s.tokens, &s.token_points, &queries, &s.colours).unwrap();
    let drift =
        before.iter().zip(&queries).flat_map(|(p, q)| p.iter().map(move |x| dist(x, q))).fold(0.0, f32::max);
    assert!(drift < 0.05, "an untrained tracker moves a query by {drift}");
    let error = |pred: &[Track]| mean_l2(pred, &s.tracks);
    let static_error = error(&before);
    for step in 1..=80u64 {
        zero(&gpu, &t);
        t.accumulate(&[&s], &mut [Rng::new(step)], 1.0).unwrap();
        let (lr, adamw) = (t.optimisation().learning_rate(step), t.adamw);
        let mut rec = gpu.recorder().unwrap();
        t.store.adamw_step(&mut rec, &adamw, lr, Some(1.0)).unwrap();
        rec.submit().unwrap();
    }
    let trained = error(&t.predict(&s.tokens, &s.token_points, &queries, &s.colours).unwrap());
    if std::env::var_os("VELOX_TEST_VERBOSE").is_some() {
        eprintln!("tiny tracker, 80 steps: mean L2 {static_error:.4} (static) -> {trained:.4}");
    }
    assert!(trained < 0.3 * static_error, "mean L2 {static_error} (static) -> {trained}");
}

/// Two scenes with the same queries, colours and token points whose tracks run opposite ways:
/// only the tokens tell them apart. Trained on both, the tracker follows each scene's motion
/// from its own tokens (nearer its own truth than the other's, and well under the static
/// baseline), and does clearly worse from the other scene's tokens or from zero tokens. Would
/// catch a tracker that does not read its tokens (its cross-attention's output zeroed, a
/// wrong token gradient that leaves them unlearned), which the one-scene test cannot.
#[test]
fn each_scene_is_tracked_from_its_own_tokens() {
    let gpu = gpu();
    let cfg = TrackerConfig { queries_per_sample: 128, ..TrackerConfig::tiny() };
    let mut t = Tracker::new(&gpu, &cfg, 3).unwrap();
    let scenes = [scene(&gpu, 6, 100, 200, 1.0), scene(&gpu, 6, 200, 200, -1.0)];
    let queries: Vec<[f32; 3]> = scenes[0].tracks.iter().map(|t| t[0]).collect();
    assert_eq!(queries, scenes[1].tracks.iter().map(|t| t[0]).collect::<Vec<_>>());
    trainer_losses(&mut t, &[&scenes[0], &scenes[1]], STEPS, Precision::F32);
    let error = |pred: &[Track], truth: &TrackSample| mean_l2(pred, &truth.tracks);
    let fixed: Vec<Track> = queries.iter().map(|&q| [q; 24]).collect();
    let zeros = Tensor::from_slice(&gpu, &[48, 32], &vec![0f32; 48 * 32]).unwrap();
    for (i, s) in scenes.iter().enumerate() {
        let other = &scenes[1 - i];
        let track = |tokens: &Tensor| t.predict(tokens, &s.token_points, &queries, &s.colours).unwrap();
        let own = track(&s.tokens);
        let (e_own, e_other) = (error(&own, s), error(&own, other));
        let e_static = error(&fixed, s);
        let e_swapped = error(&track(&other.tokens), s);
        let e_zero = error(&track(&zeros), s);
        if verbose() {
            eprintln!(
                "scene {i}: mean L2 to its truth {e_own:.4} (to the other's {e_other:.4}, static {e_static:.4}); \
                 from the other's tokens {e_swapped:.4}, from zero tokens {e_zero:.4}"
            );
        }
        assert!(e_own < 0.1 * e_static, "scene {i}: {e_own} against the static baseline's {e_static}");
        assert!(e_own < 0.1 * e_other, "scene {i}: {e_own} to its own truth, {e_other} to the other's");
        assert!(
            e_swapped > 3.0 * e_own,
            "scene {i}: {e_swapped} from the other's tokens, {e_own} from its own"
        );
        assert!(e_zero > 10.0 * e_own, "scene {i}: {e_zero} from zero tokens, {e_own} from its own");
    }
}

const STEPS: u64 = 150;

/// The mean distance between predicted and true positions over every query and frame.
fn mean_l2(pred: &[Track], truth: &[Track]) -> f64 {
    let n = (pred.len() * 24) as f64;
    pred.iter().zip(truth).flat_map(|(p, t)| p.iter().zip(t).map(|(a, b)| dist(a, b) as f64)).sum::<f64>() / n
}

fn dist(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>().sqrt()
}

#[test]
fn queries_are_tracked_on_their_own() {
    let gpu = gpu();
    for query_colour in [false, true] {
        queries_alone(&gpu, &TrackerConfig { query_colour, ..TrackerConfig::tiny() });
    }
}

fn queries_alone(gpu: &Gpu, cfg: &TrackerConfig) {
    let t = Tracker::new(gpu, cfg, 7).unwrap();
    let s = sample(gpu, 8, 30);
    let queries: Vec<[f32; 3]> = s.tracks.iter().map(|t| t[0]).collect();
    let together = t.predict(&s.tokens, &s.token_points, &queries, &s.colours).unwrap();
    for i in [0, 13, 29] {
        let alone = t.predict(&s.tokens, &s.token_points, &queries[i..i + 1], &s.colours[i..i + 1]).unwrap();
        let flat = |t: &Track| t.iter().flatten().copied().collect::<Vec<f32>>();
        assert_nmse(&format!("query {i} alone"), &flat(&alone[0]), &f64s(&flat(&together[i])), 1e-10);
    }
    // A tracker that reads the colour tracks a query of another colour elsewhere; one that
    // does not, to the bit where it did.
    let recoloured = t.predict(&s.tokens, &s.token_points, &queries[..1], &[[1.0, 0.0, 0.5]]).unwrap();
    assert_eq!(recoloured[0] == together[0], !cfg.query_colour, "query colour {}", cfg.query_colour);
    let e = t.predict(&s.tokens, &s.token_points, &[[0.0, 1.5, 0.0]], &[[0.5; 3]]).unwrap_err().to_string();
    assert!(e.contains("query 0"), "{e}");
    let e = t.predict(&s.tokens, &s.token_points, &queries[..2], &s.colours[..1]).unwrap_err().to_string();
    assert!(e.contains("1 colours for 2 queries"), "{e}");
    let e = TrackSample::new(s.tokens.clone(), s.token_points.clone(), Vec::new(), Vec::new())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("no tracks"), "{e}");
    let mut colours = s.colours.clone();
    colours[3] = [0.2, f32::NAN, 0.1];
    let e = TrackSample::new(s.tokens.clone(), s.token_points.clone(), s.tracks.clone(), colours)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("query 3"), "{e}");
}

#[test]
fn occlusion_is_the_depth_test_of_the_data() {
    use velox::engine::ops::raster::Camera;
    // A 4 x 2 image at the origin looking down +z, focal length 100; its depth frame shows a
    // surface at depth 2 on the left half and the background on the right.
    let cam = Camera { fx: 100.0, fy: 100.0, cx: 2.0, cy: 1.0, ..Camera::identity(60.0, 4, 2) };
    let depth = [2.0, 2.0, 0.0, 0.0, 2.0, 2.0, 0.0, 0.0];
    let sees = |u: f32, v: f32, z: f32| cam.sees(cam.unproject(u, v, z), &depth);
    // In front of, on, and a hair behind the surface (within 3 footprints: 3 * 2 / 100).
    assert!(sees(0.5, 0.5, 1.0));
    assert!(sees(1.5, 1.5, 2.05));
    // Behind it by more than 3 footprints.
    assert!(!sees(1.5, 1.5, 2.1));
    // Over the background: unseen, as the data counts it (no surface shows it).
    assert!(!sees(2.5, 0.5, 1.0));
    // Outside the image, or behind the camera.
    assert!(!sees(4.0, 0.5, 1.0));
    assert!(!sees(-0.1, 0.5, 1.0));
    assert!(!cam.sees([0.0, 0.0, -1.0], &depth));
}

#[test]
fn the_paper_config_counts_about_123_million_parameters() {
    let m = Tracker::declare(&gpu(), &TrackerConfig::paper()).unwrap().num_parameters() as f64 / 1e6;
    assert!((m - 123.0).abs() < 0.05 * 123.0, "{m:.2} M");
}

#[test]
fn f16_training_follows_f32() {
    // The tiny tracker trained by the library trainer 60 steps on one scene from the same start
    // in f32 and in f16 (f16 operands of every product forward and backward, f32 masters, the
    // loss scaled by 2^16). Two runs that round differently drift apart once the loss is down
    // in its own step-to-step noise (here 20x below its start), so they are held together step
    // by step over the first 20 steps and by the level they reach over the last 20.
    let gpu = gpu();
    let cfg = TrackerConfig::tiny();
    let s = sample(&gpu, 6, 400);
    let losses = |precision| trainer_losses(&mut Tracker::new(&gpu, &cfg, 3).unwrap(), &[&s], 60, precision);
    let (full, half) = (losses(Precision::F32), losses(Precision::F16));
    let (worst, mean) = relative_gaps(&full[..20], &half[..20]);
    let (end_full, end_half) = (mean_of(&full[40..]), mean_of(&half[40..]));
    eprintln!(
        "tracker f16 against f32, 60 steps: loss {:.4} -> {end_half:.4} (f32 {:.4} -> {end_full:.4}, means of \
         the last 20 steps); over the first 20 steps a relative difference of at most {worst:.2e}, mean {mean:.2e}",
        half[0], full[0]
    );
    // Measured on lavapipe: at most 1.2e-2, mean 4e-3 over the first 20 steps (0.066 -> 0.010);
    // the last 20 steps 3.6e-3 against f32's 3.8e-3.
    assert!(worst < 0.03 && mean < 0.01, "f16 strays from f32: worst {worst:.3e}, mean {mean:.3e}");
    assert!(end_half < 1.1 * end_full, "f16 ends at {end_half:.3e} against f32's {end_full:.3e}");
    assert!(end_full < 0.2 * full[0], "the run must learn: {full:?}");
}

/// Would catch: a tracker step recorded while the last runs that differs from one recorded
/// after it.
#[test]
fn steps_recorded_ahead_are_the_same_steps() {
    let gpu = gpu();
    let s = sample(&gpu, 6, 100);
    recorded_ahead_is_the_same(|| Tracker::new(&gpu, &TrackerConfig::tiny(), 3).unwrap(), &[&s], 4);
}

/// Would catch: a host wait added to the tracker's training step (a pass submitted on its own,
/// a result read with a copy of its own).
#[test]
fn a_training_step_is_one_submission() {
    // This test's device while it runs, so that no other test's submissions are counted.
    let Some(gpu) = counting_gpu() else { return };
    let s = sample(&gpu, 6, 100);
    let mut t = Tracker::new(&gpu, &TrackerConfig::tiny(), 3).unwrap();
    let before = gpu.submits();
    // The forward and backward passes and the update in one recording: the loss and the
    // gradient norm come back with it.
    trainer_losses(&mut t, &[&s], 3, Precision::F32);
    assert_eq!(gpu.submits() - before, 3);
}
