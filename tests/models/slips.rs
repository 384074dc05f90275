//! Checks aimed at plausible one-line slips that the rest of the suite would pass, or catch
//! only by accident in a slow or unrelated test: a regulariser or a noise that reaches one of
//! its consumers and not another (the autoencoder's token noise, token loss weight, encoder
//! subset and flow times, the surface decoder's and the generator's flow noise, the
//! generator's condition dropout, the voxel decoder's dilation), the weight-decay layout of
//! every real model at its tiny and paper configs, the generator's classifier-free guidance,
//! and the tracker's token path in training. Each runs the tiny configs for a step or two.

use crate::common;
use common::*;
use velox::data::format::write_scene;
use velox::data::{procedural, read_scene, SynthOptions};
use velox::engine::ops::adamw::AdamWConfig;
use velox::models::config::{AutoencoderConfig, GeneratorConfig, TrackerConfig, VoxelConfig};
use velox::models::params::{ParamBuilder, ParamInfo, ParamStore};
use velox::models::velox::autoencoder::{Autoencoder, TrainScene};
use velox::models::velox::dinov2::PATCH_VALUES;
use velox::models::velox::generator::{Condition, GenSample, GenerateSpec, Generator};
use velox::models::velox::surface::{FlowNoise, Sampler, SurfaceDecoder};
use velox::models::velox::tracker::{Track, TrackSample, Tracker};
use velox::models::velox::voxels::{VoxelDecoder, VoxelSample, FRAME_WORDS, GRID};
use velox::tasks::training::train_scene;

// ---------------------------------------------------------------------------------------------
// Regularisers and noise: each reaches every consumer it should, and no other.

/// `on` differs from `off` by more than f32 rounding could make it: the switch reached it.
#[track_caller]
fn moved(what: &str, off: f64, on: f64) {
    assert!(
        (on - off).abs() > 1e-5 * off.abs().max(1e-12),
        "{what}: {off:e} with the switch off, {on:e} with it on: the switch does not reach it"
    );
}

/// `on` is `off` to the bit: the switch did not reach it.
#[track_caller]
fn unmoved(what: &str, off: f64, on: f64) {
    assert!(
        on.to_bits() == off.to_bits(),
        "{what}: {off:e} with the switch off, {on:e} with it on: the switch reaches what it must not"
    );
}

/// The gradient `on` differs from `off` by more than f32 rounding could make it.
#[track_caller]
fn grads_moved(what: &str, off: &[f32], on: &[f32]) {
    let e = nmse(on, &f64s(off));
    assert!(e > 1e-8, "{what}: the gradient moved by nmse {e:.2e} only: the switch does not reach it");
}

/// The gradient `on` is `off` to the bit.
#[track_caller]
fn grads_unmoved(what: &str, off: &[f32], on: &[f32]) {
    let diff = off.iter().zip(on).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
    assert!(
        diff == 0,
        "{what}: {diff} of {} gradient values moved: the switch reaches what it must not",
        on.len()
    );
}

/// Procedural scene 3 at 32 x 32 with 4000 points, as the autoencoder's own tests make it.
fn ae_scene(gpu: &Gpu, name: &str) -> TrainScene {
    let dir = std::env::temp_dir().join(format!("velox-slips-{}-{name}", std::process::id()));
    let (_, mesh) = procedural::scene(3, None).unwrap();
    let opts = SynthOptions { res: 32, points: 4000, supersample: 1, tracks: 8, ..Default::default() };
    write_scene(gpu, &mesh, "test", None, 3, &opts, &dir, &mut |_| {}).unwrap();
    let s = read_scene(&dir, true).unwrap();
    let t = train_scene(gpu, &s).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    t
}

/// One micro-batch of the tiny autoencoder: its loss terms and its parts' gradients.
struct AeStep {
    surface: f64,
    image: f64,
    tokens: f64,
    encoder_grads: Vec<f32>,
    surface_grads: Vec<f32>,
    gaussian_grads: Vec<f32>,
}

/// A fresh autoencoder of `cfg` with every parameter drawn at random (the same values for
/// every config that declares the same parameters), so that neither decoder's adaLN-Zero maps
/// nor its small-started output hides the tokens from its loss; then one micro-batch of
/// `scene` with the draws of seed 31.
fn ae_step(cfg: &AutoencoderConfig, scene: &TrainScene) -> AeStep {
    let gpu = scene.cloud.gpu().clone();
    let mut ae = Autoencoder::new(&gpu, cfg, 1).unwrap();
    randomize_params(&ae.store, 11, 0.6);
    let mut rec = gpu.recorder().unwrap();
    ae.store.zero_grads(&mut rec).unwrap();
    rec.submit().unwrap();
    let losses = ae.accumulate(&[scene], &mut [Rng::new(31)], 1.0).unwrap();
    let term =
        |name: &str| losses.terms.iter().find(|t| t.0 == name).unwrap_or_else(|| panic!("no {name} term")).1;
    let flat: Vec<f32> = ae.store.flat_grads().read().unwrap();
    let part = |prefix: &str| -> Vec<f32> {
        let infos = ae.store.infos().iter().filter(|i| i.name.starts_with(prefix));
        infos.flat_map(|i| flat[i.offset..i.offset + i.numel].iter().copied()).collect()
    };
    AeStep {
        surface: term("surface"),
        image: term("image"),
        tokens: term("tokens"),
        encoder_grads: part("encoder."),
        surface_grads: part("surface."),
        gaussian_grads: part("gaussians."),
    }
}

/// The token noise (0.3, against none, every draw the same) reaches both decoders: the
/// surface loss and the image loss, each decoder's own term, move, and so do both decoders'
/// gradients and the encoder's; the token loss, which reads the clean tokens, stays to the bit.
/// Would catch the clean tokens `s` fed to either decoder in place of the noised ones, or the
/// token loss computed on the noised tokens. (At the configs' 0.001 the decoders' losses move
/// less than f32 resolves: measured, the surface loss not at all and the image loss by 5e-7;
/// at 0.3, about the tokens' own size, by 7e-5 and 3e-4.)
#[test]
fn token_noise_reaches_both_decoders_and_not_the_token_loss() {
    let gpu = gpu();
    let scene = ae_scene(&gpu, "noise");
    let mut on = AutoencoderConfig::tiny();
    on.encoder.token_noise = 0.3;
    let mut off = on.clone();
    off.encoder.token_noise = 0.0;
    let (a, b) = (ae_step(&off, &scene), ae_step(&on, &scene));
    if verbose() {
        eprintln!(
            "token noise: surface {:e} -> {:e}, image {:e} -> {:e}, tokens {:e} -> {:e}",
            a.surface, b.surface, a.image, b.image, a.tokens, b.tokens
        );
    }
    moved("token noise: the surface decoder's loss", a.surface, b.surface);
    moved("token noise: the Gaussian decoder's image loss", a.image, b.image);
    unmoved("token noise: the token loss", a.tokens, b.tokens);
    grads_moved("token noise: the surface decoder's", &a.surface_grads, &b.surface_grads);
    grads_moved("token noise: the Gaussian decoder's", &a.gaussian_grads, &b.gaussian_grads);
    grads_moved("token noise: the encoder's", &a.encoder_grads, &b.encoder_grads);
}

/// The token loss weight gamma (the tiny config's 1e-4, against 0) reaches the token loss,
/// linearly (twice gamma, twice the term), and the encoder's gradient, and nothing else: both
/// decoders' losses and gradients stay to the bit. Would catch gamma left out of the token
/// loss, the token loss's gradient left out of the encoder's (the decoders' token gradients
/// written over it), or the token loss's weight applied to a decoder's term.
#[test]
fn the_token_loss_weight_reaches_the_token_loss_and_the_encoder_alone() {
    let gpu = gpu();
    let scene = ae_scene(&gpu, "gamma");
    let on = AutoencoderConfig::tiny();
    assert!(on.encoder.token_reg > 0.0);
    let with = |gamma: f32| {
        let mut c = on.clone();
        c.encoder.token_reg = gamma;
        c
    };
    let (a, b) = (ae_step(&with(0.0), &scene), ae_step(&on, &scene));
    let double = ae_step(&with(2.0 * on.encoder.token_reg), &scene);
    if verbose() {
        eprintln!("token loss weight: tokens {:e} -> {:e} (doubled {:e})", a.tokens, b.tokens, double.tokens);
    }
    assert_eq!(a.tokens, 0.0, "the token loss at gamma 0");
    moved("token loss weight: the token loss", a.tokens, b.tokens);
    assert!(
        (double.tokens - 2.0 * b.tokens).abs() <= 1e-6 * b.tokens,
        "the token loss at twice gamma is {:e}, at gamma {:e}: not linear in gamma",
        double.tokens,
        b.tokens
    );
    unmoved("token loss weight: the surface decoder's loss", a.surface, b.surface);
    unmoved("token loss weight: the image loss", a.image, b.image);
    grads_moved("token loss weight: the encoder's", &a.encoder_grads, &b.encoder_grads);
    grads_unmoved("token loss weight: the surface decoder's", &a.surface_grads, &b.surface_grads);
    grads_unmoved("token loss weight: the Gaussian decoder's", &a.gaussian_grads, &b.gaussian_grads);
}

/// The range of the surface decoder's flow times (`t_min` 0.3 against the tiny config's
/// 1e-3, the same uniform draws) reaches the surface decoder's loss and gradient and the
/// encoder's gradient (through the tokens' gradient), and nothing else: the image and token
/// losses and the Gaussian decoder's gradient stay to the bit. Would catch the flow times
/// drawn apart from the config, or the surface decoder's noise spilling into the Gaussian
/// decoder's draws.
#[test]
fn the_flow_time_range_reaches_the_surface_decoder_alone() {
    let gpu = gpu();
    let scene = ae_scene(&gpu, "t-min");
    let off = AutoencoderConfig::tiny();
    let mut on = off.clone();
    on.surface.t_min = 0.3;
    let (a, b) = (ae_step(&off, &scene), ae_step(&on, &scene));
    moved("flow time range: the surface decoder's loss", a.surface, b.surface);
    unmoved("flow time range: the image loss", a.image, b.image);
    unmoved("flow time range: the token loss", a.tokens, b.tokens);
    grads_moved("flow time range: the surface decoder's", &a.surface_grads, &b.surface_grads);
    grads_moved("flow time range: the encoder's", &a.encoder_grads, &b.encoder_grads);
    grads_unmoved("flow time range: the Gaussian decoder's", &a.gaussian_grads, &b.gaussian_grads);
}

/// The encoder's subset (`encoder_points`): 40 of the scene's 4000 points move every term
/// (the encoder's tokens feed both decoders and the token loss), a "subset" of the whole cloud
/// or more is the whole cloud, to the bit, and the encoder reads nothing outside its subset: a
/// point's colour (which only the encoder reads) changed leaves every term as it was, to the
/// bit, for a point outside the subset, where with the whole cloud encoded the same change
/// moves a term. Would catch the subset never drawn, or drawn and the whole cloud
/// encoded all the same.
#[test]
fn the_encoder_subset_reaches_every_term_and_is_all_the_encoder_reads() {
    let gpu = gpu();
    let scene = ae_scene(&gpu, "subset");
    let n = scene.cloud_host.len() / 7;
    let with = |points: usize| AutoencoderConfig { encoder_points: points, ..AutoencoderConfig::tiny() };
    let whole = ae_step(&with(0), &scene);
    let sub = ae_step(&with(40), &scene);
    moved("encoder subset: the surface decoder's loss", whole.surface, sub.surface);
    moved("encoder subset: the image loss", whole.image, sub.image);
    moved("encoder subset: the token loss", whole.tokens, sub.tokens);
    let all = ae_step(&with(n), &scene);
    for (what, a, b) in [("surface", whole.surface, all.surface), ("image", whole.image, all.image)] {
        unmoved(&format!("a subset of all {n} points: the {what} loss"), a, b);
    }
    unmoved(&format!("a subset of all {n} points: the token loss"), whole.tokens, all.tokens);

    // Point `row` recoloured: the same draws (they depend on the counts alone), another input.
    let recoloured = |row: usize| {
        let mut cloud = scene.cloud_host.clone();
        for c in 3..6 {
            cloud[row * 7 + c] = 1.0 - cloud[row * 7 + c];
        }
        TrainScene::new(&gpu, cloud, scene.cameras.clone(), scene.images.clone()).unwrap()
    };
    // 40 of 4000: a given point is outside the subset with probability 0.99. A point the
    // encoder reads may still move the token loss by less than f32 resolves, so a point counts
    // as unread only where all three terms stay to the bit.
    let terms = |s: &AeStep| [s.surface, s.image, s.tokens].map(f64::to_bits);
    let rows = 0..8;
    let outside = rows.clone().find(|&row| terms(&ae_step(&with(40), &recoloured(row))) == terms(&sub));
    let Some(row) = outside else {
        panic!(
            "recolouring each of points {rows:?} moved a loss term: the encoder reads more than its 40 points"
        )
    };
    // The same point is read when the whole cloud is encoded.
    let read = ae_step(&with(0), &recoloured(row));
    assert!(
        terms(&read) != terms(&whole),
        "point {row} recoloured, the whole cloud encoded: every term stays as it was, so this test cannot \
         see a point read"
    );
}

/// The surface decoder's flow noise reaches all three of its readers: the training loss
/// (`flow_loss`) at points x, noise eps and flow times t is the mean of |v - u|^2 with
/// x_t = eps + t (x - eps) and u = x - eps made on the host and v the decoder's velocity at
/// those x_t and t. Would catch eps left out of the network's input or of the target, or the
/// time embedding reading other times than x_t was made with.
#[test]
fn the_surface_flow_noise_reaches_input_target_and_time() {
    let gpu = gpu();
    let cfg = AutoencoderConfig::tiny();
    let d = cfg.encoder.token_dim;
    let (store, dec) = SurfaceDecoder::standalone(&gpu, &cfg.surface, d, 5).unwrap();
    randomize_params(&store, 6, 0.6);
    let mut rng = Rng::new(7);
    let (n, k, tau) = (40usize, 6usize, 0.12f32);
    let x = rng.uniform_vec(n * 3, -0.8, 0.8);
    let tokens = Tensor::from_slice(&gpu, &[k, d], &rng.normal_vec(k * d)).unwrap();
    let (eps, t) = (rng.normal_vec(n * 3), rng.uniform_vec(n, 0.05, 0.95));
    let noise = FlowNoise::from_host(&gpu, &eps, &t).unwrap();
    let x_dev = Tensor::from_slice(&gpu, &[n, 3], &x).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let (loss, _, _) = dec.flow_loss(&mut rec, &x_dev, tau, &tokens, &noise, 1.0).unwrap();
    rec.submit().unwrap();
    let loss = loss.read::<f32>().unwrap()[0] as f64;
    // The host's x_t in the order the device computes it: u = x - eps, x_t = eps + t u.
    let u: Vec<f32> = x.iter().zip(&eps).map(|(a, b)| a - b).collect();
    let x_t: Vec<f32> = (0..n * 3).map(|i| eps[i] + t[i / 3] * u[i]).collect();
    let mut rec = gpu.recorder().unwrap();
    let x_t = Tensor::from_slice(&gpu, &[n, 3], &x_t).unwrap();
    let (v, _) =
        dec.forward(&mut rec, &x_t, tau, &Tensor::from_slice(&gpu, &[n], &t).unwrap(), &tokens).unwrap();
    rec.submit().unwrap();
    let v: Vec<f32> = v.read().unwrap();
    let want = v.iter().zip(&u).map(|(&a, &b)| (a as f64 - b as f64).powi(2)).sum::<f64>() / (n * 3) as f64;
    if verbose() {
        eprintln!("surface flow loss {loss:e}, from its velocity {want:e}");
    }
    assert!(
        (loss - want).abs() <= 1e-5 * want,
        "the surface decoder's flow loss {loss:e}, from its velocity at x_t and t {want:e}"
    );
}

/// The voxel decoder's dilation (`dilate` 1 against 0: the fine stage also trains on the empty
/// cells next to the surface) reaches the fine stage's loss and nothing else: the coarse
/// stage's loss stays to the bit. Would catch the dilation left out of the cells the fine stage
/// trains on.
#[test]
fn the_voxel_dilation_reaches_the_fine_stage_alone() {
    let gpu = gpu();
    // A ball of radius 6 voxels moving across the grid.
    let mut words = vec![0u64; 24 * FRAME_WORDS];
    for f in 0..24 {
        let c = [20.0 + f as f32, 30.0, 34.0 - 0.5 * f as f32];
        for i in 0..GRID * GRID * GRID {
            let p = [i % GRID, i / GRID % GRID, i / (GRID * GRID)];
            if (0..3).map(|a| (p[a] as f32 + 0.5 - c[a]).powi(2)).sum::<f32>() <= 36.0 {
                words[f * FRAME_WORDS + i / 64] |= 1 << (i % 64);
            }
        }
    }
    let tokens = Tensor::from_slice(&gpu, &[48, 32], &Rng::new(3).normal_vec(48 * 32)).unwrap();
    let sample = VoxelSample::new(tokens, words).unwrap();
    let terms = |dilate: usize| {
        let mut d = VoxelDecoder::new(&gpu, &VoxelConfig { dilate, ..VoxelConfig::tiny() }, 1).unwrap();
        randomize_params(&d.store, 4, 0.6);
        let l = d.accumulate(&[&sample], &mut [Rng::new(5)], 1.0).unwrap();
        let term = |name: &str| l.terms.iter().find(|t| t.0 == name).unwrap().1;
        (term("coarse"), term("fine"))
    };
    let (off, on) = (terms(0), terms(1));
    unmoved("dilation: the coarse stage's loss", off.0, on.0);
    moved("dilation: the fine stage's loss", off.1, on.1);
}

// ---------------------------------------------------------------------------------------------
// The generator: its flow noise, condition dropout and classifier-free guidance.

/// A scene of the generator: random tokens and a random video (patches), from `seed`.
fn gen_sample(gpu: &Gpu, cfg: &GeneratorConfig, seed: u64) -> GenSample {
    let mut rng = Rng::new(seed);
    let tokens = rng.normal_vec(cfg.tokens * cfg.token_dim);
    let patches = rng.normal_vec(cfg.cond_tokens() * PATCH_VALUES);
    GenSample {
        tokens: Tensor::from_slice(gpu, &[cfg.tokens, cfg.token_dim], &tokens).unwrap(),
        condition: Condition {
            patches: Tensor::from_slice(gpu, &[cfg.cond_tokens(), PATCH_VALUES], &patches).unwrap(),
            dino: None,
        },
    }
}

/// The tiny generator with every parameter drawn at random, so that its zero-started gates,
/// tables, cross-attention outputs and output layer let the condition and the flow time reach
/// the velocity.
fn randomised_generator(gpu: &Gpu, cfg: &GeneratorConfig) -> Generator {
    let g = Generator::new(gpu, cfg, 2).unwrap();
    let n = g.store.flat_params().numel();
    let theta: Vec<f32> = Rng::new(3).normal_vec(n).iter().map(|v| 0.2 * v).collect();
    g.store.flat_params().write(&theta).unwrap();
    g
}

/// The generator's flow noise reaches all three of its readers: the training loss
/// (`flow_loss`) at tokens x, noise eps and flow time t is the mean of |v - u|^2 with
/// x_t = eps + t (x - eps) and u = x - eps made on the host and v the velocity evaluated
/// apart at those x_t and t ([`Generator::velocity`]), for a kept and a dropped condition.
/// Would catch eps left out of the network's input or of the target, or the time embedding
/// reading another time than x_t was made with.
#[test]
fn the_generator_flow_noise_reaches_input_target_and_time() {
    let gpu = gpu();
    let cfg = GeneratorConfig::tiny();
    let g = randomised_generator(&gpu, &cfg);
    let s = gen_sample(&gpu, &cfg, 4);
    let n = cfg.tokens * cfg.token_dim;
    let mut rng = Rng::new(8);
    let (eps, t) = (rng.normal_vec(n), 0.37f32);
    let x: Vec<f32> = s.tokens.read().unwrap();
    let u: Vec<f32> = x.iter().zip(&eps).map(|(a, b)| a - b).collect();
    let x_t: Vec<f32> = eps.iter().zip(&u).map(|(e, u)| e + u * t).collect();
    let x_t = Tensor::from_slice(&gpu, &[cfg.tokens, cfg.token_dim], &x_t).unwrap();
    for keep in [true, false] {
        let mut rec = gpu.recorder().unwrap();
        let (loss, _, _) = g.flow_loss(&mut rec, &[&s], &eps, &[t], &[keep], 1.0).unwrap();
        rec.submit().unwrap();
        let loss = loss.read::<f32>().unwrap()[0] as f64;
        let v: Vec<f32> = g.velocity(&x_t, t, &s.condition, keep).unwrap().read().unwrap();
        let want = v.iter().zip(&u).map(|(&a, &b)| (a as f64 - b as f64).powi(2)).sum::<f64>() / n as f64;
        if verbose() {
            eprintln!("generator flow loss (condition kept {keep}) {loss:e}, from its velocity {want:e}");
        }
        assert!(
            (loss - want).abs() <= 1e-5 * want,
            "condition kept {keep}: the generator's flow loss {loss:e}, from its velocity at x_t and t {want:e}"
        );
    }
}

/// Condition dropout reaches the condition in both passes: at dropout 1 the training loss is
/// the same, to the bit, whatever the video, and the video's embeddings (`rgb`, `cond`) get
/// no gradient; at 0 another video moves the loss and both get gradients. Would catch the
/// dropout's mask left out of the forward pass or out of the backward pass.
#[test]
fn condition_dropout_reaches_the_condition_in_both_passes() {
    let gpu = gpu();
    let (a, b) =
        (gen_sample(&gpu, &GeneratorConfig::tiny(), 4), gen_sample(&gpu, &GeneratorConfig::tiny(), 5));
    // Scene b with scene a's tokens: only the video differs.
    let b = GenSample { tokens: a.tokens.clone(), condition: b.condition };
    for dropout in [0.0, 1.0] {
        let cfg = GeneratorConfig { cond_dropout: dropout, ..GeneratorConfig::tiny() };
        let mut g = randomised_generator(&gpu, &cfg);
        let mut run = |s: &GenSample| {
            let mut rec = gpu.recorder().unwrap();
            g.store.zero_grads(&mut rec).unwrap();
            rec.submit().unwrap();
            let l = g.accumulate(&[s], &mut [Rng::new(9)], 1.0).unwrap().total();
            let grad = |name: &str| g.store.grad(name).unwrap().read::<f32>().unwrap();
            (l, grad("rgb.w"), grad("cond.w"))
        };
        let (la, rgb, cond) = run(&a);
        let (lb, _, _) = run(&b);
        let zero = |g: &[f32]| g.iter().all(|&v| v == 0.0);
        if dropout == 1.0 {
            unmoved("dropout 1: the loss under another video", la, lb);
            assert!(zero(&rgb) && zero(&cond), "dropout 1: the dropped video's embeddings got a gradient");
        } else {
            moved("dropout 0: the loss under another video", la, lb);
            assert!(!zero(&rgb) && !zero(&cond), "dropout 0: the video's embeddings got no gradient");
        }
    }
}

/// The guided velocity `v_null + w (v_cond - v_null)` (host, f64) of two velocities.
fn guided(v_cond: &[f32], v_null: &[f32], w: f32) -> Vec<f64> {
    v_cond.iter().zip(v_null).map(|(&c, &n)| n as f64 + w as f64 * (c as f64 - n as f64)).collect()
}

/// Classifier-free guidance, as docs/models.md and the sampler define it (`GenerateSpec`):
/// one Euler step from the sampler's noise x_0 (its seed's normals) at t = 0 is
/// `x_1 = x_0 + v_null + w (v_cond - v_null)`, that is `(1 - w) v_null + w v_cond`, with
/// v_cond and v_null evaluated apart ([`Generator::velocity`]: the null condition as training's
/// dropout makes it, every row zero, where the sampler attends to one zero row), within f32
/// rounding, at w = 0 (the null condition alone), 1 (the conditional network alone, unguided),
/// 3 (the paper's scale) and 7.5; and one Heun step at w = 3 is the trapezoid of the guided
/// velocities at x_0 and at its Euler prediction. Would catch the guidance difference reversed
/// (v_cond and v_null swapped), the scale on the wrong term, the null condition read from the
/// video, and the unguided path run at w = 1 guided or the other way round.
#[test]
fn one_guided_step_is_the_guided_combination_of_the_two_velocities() {
    let gpu = gpu();
    let cfg = GeneratorConfig::tiny();
    let g = randomised_generator(&gpu, &cfg);
    let s = gen_sample(&gpu, &cfg, 40);
    let (k, d) = (cfg.tokens, cfg.token_dim);
    let seed = 11;
    let x0: Vec<f32> = Rng::new(seed).normal_vec(k * d);
    let x0_dev = Tensor::from_slice(&gpu, &[k, d], &x0).unwrap();
    let velocities = |x: &Tensor, t: f32| -> (Vec<f32>, Vec<f32>) {
        let v = |keep| g.velocity(x, t, &s.condition, keep).unwrap().read::<f32>().unwrap();
        (v(true), v(false))
    };
    let (vc, vn) = velocities(&x0_dev, 0.0);
    // The two differ well beyond rounding, so a swap cannot pass.
    assert!(
        nmse(&vc, &f64s(&vn)) > 1e-3,
        "the condition barely moves the velocity: nmse {:.2e}",
        nmse(&vc, &f64s(&vn))
    );
    let spec =
        |w: f32, sampler| GenerateSpec { steps: 1, sampler, guidance: w, seed, precision: Precision::F32 };
    for w in [0.0f32, 1.0, 3.0, 7.5] {
        let got: Vec<f32> = g.generate(&s.condition, &spec(w, Sampler::Euler)).unwrap().read().unwrap();
        let want: Vec<f64> = guided(&vc, &vn, w).iter().zip(&x0).map(|(v, &x)| x as f64 + v).collect();
        assert_nmse(&format!("one Euler step at guidance {w}"), &got, &want, 1e-11);
    }
    // Heun: x_1 = x_0 + (g(x_0, 0) + g(x_0 + g(x_0, 0), 1)) / 2, g the guided velocity.
    let w = 3.0;
    let g0 = guided(&vc, &vn, w);
    let predicted: Vec<f32> = x0.iter().zip(&g0).map(|(&x, &v)| x + v as f32).collect();
    let (vc1, vn1) = velocities(&Tensor::from_slice(&gpu, &[k, d], &predicted).unwrap(), 1.0);
    let g1 = guided(&vc1, &vn1, w);
    let want: Vec<f64> = (0..k * d).map(|i| x0[i] as f64 + 0.5 * (g0[i] + g1[i])).collect();
    let got: Vec<f32> = g.generate(&s.condition, &spec(w, Sampler::Heun)).unwrap().read().unwrap();
    assert_nmse("one Heun step at guidance 3", &got, &want, 1e-11);
}

// ---------------------------------------------------------------------------------------------
// The tracker's token path in training.

/// A tracking scene: `n` tracks moving with a drift and a shear, 48 tokens of its own from
/// `token_seed`, token points and colours from `seed`.
fn track_scene(gpu: &Gpu, seed: u64, token_seed: u64, n: usize) -> TrackSample {
    let mut rng = Rng::new(seed);
    let tracks: Vec<Track> = (0..n)
        .map(|_| {
            let q = [0; 3].map(|_| rng.range(-0.8, 0.8) as f32);
            std::array::from_fn(|f| {
                let s = f as f32 / 23.0;
                [q[0] + 0.2 * s, q[1] + 0.3 * s * q[0], q[2] - 0.1 * s * s]
            })
        })
        .collect();
    let points: Vec<f32> = (0..48)
        .flat_map(|i| {
            [0; 3].map(|_| rng.range(-1.0, 1.0) as f32).into_iter().chain([(i % 24) as f32 / 100.0])
        })
        .collect();
    let colours = (0..n).map(|_| [0; 3].map(|_| rng.uniform() as f32)).collect();
    let tokens = Rng::new(token_seed).normal_vec(48 * 32);
    TrackSample::new(
        Tensor::from_slice(gpu, &[48, 32], &tokens).unwrap(),
        Tensor::from_slice(gpu, &[48, 4], &points).unwrap(),
        tracks,
        colours,
    )
    .unwrap()
}

/// Prediction's error on a scene: the mean over its queries, frames and coordinates of
/// |predicted - true| (the L1 loss training reports).
fn predicted(t: &Tracker, s: &TrackSample) -> f64 {
    let queries: Vec<[f32; 3]> = s.tracks.iter().map(|t| t[0]).collect();
    let pred = t.predict(&s.tokens, &s.token_points, &queries, &s.colours).unwrap();
    let sum: f64 = pred
        .iter()
        .zip(&s.tracks)
        .flat_map(|(p, t)| p.iter().flatten().zip(t.iter().flatten()).map(|(a, b)| (a - b).abs() as f64))
        .sum();
    sum / (s.tracks.len() * 24 * 3) as f64
}

/// The training loss of one micro-batch of `samples` (each scene's generator seeded apart).
fn trained(t: &mut Tracker, samples: &[&TrackSample]) -> f64 {
    let mut rec = t.store.recorder().unwrap();
    t.store.zero_grads(&mut rec).unwrap();
    rec.submit().unwrap();
    let mut rngs: Vec<Rng> = (0..samples.len()).map(|i| Rng::new(9 + i as u64)).collect();
    t.accumulate(samples, &mut rngs, 1.0).unwrap().total()
}

/// The tracker's training path reads the tokens (and token points) that prediction reads: the
/// training loss of a scene (L1, every track drawn) equals the error of [`Tracker::predict`]'s
/// tracks from the same tokens and points, for the scene's own tokens, another scene's and
/// zeros, which give three different losses; new token points move the loss (still matching)
/// with `token_positions` and leave it to the bit without; a batch of two scenes is the sum of
/// their prediction errors. In both `token_positions` settings, with the parameters
/// randomised (the head's small start would hide the tokens). Would catch the training path
/// reading zeros, or another scene's rows, for its tokens or their points: no gradient check
/// can see that (the forward and backward passes agree), and the learning tests see it only
/// through prediction.
#[test]
fn the_tracker_trains_on_the_tokens_it_predicts_from() {
    let gpu = gpu();
    for token_positions in [false, true] {
        let cfg = TrackerConfig { token_positions, ..TrackerConfig::tiny() };
        let mut t = Tracker::new(&gpu, &cfg, 2).unwrap();
        randomize_params(&t.store, 12, 0.6);
        let own = track_scene(&gpu, 4, 4, 30);
        assert!(own.tracks.len() <= cfg.queries_per_sample, "every track is drawn");
        let other = track_scene(&gpu, 5, 5, 20);
        let zeros = Tensor::from_slice(&gpu, &[48, 32], &vec![0f32; 48 * 32]).unwrap();
        let with = |s: &TrackSample, tokens: &Tensor, points: &Tensor| {
            TrackSample::new(tokens.clone(), points.clone(), s.tracks.clone(), s.colours.clone()).unwrap()
        };
        let what = format!("token positions {token_positions}");
        let close = |what: &str, got: f64, want: f64| {
            assert!(
                (got - want).abs() <= 1e-5 * want,
                "{what}: the training loss {got:e}, prediction's error from the same tokens {want:e}"
            );
        };
        let scenes = [
            ("its own tokens", with(&own, &own.tokens, &own.token_points)),
            ("another scene's tokens", with(&own, &other.tokens, &own.token_points)),
            ("zero tokens", with(&own, &zeros, &own.token_points)),
            ("other token points", with(&own, &own.tokens, &other.token_points)),
        ];
        let mut losses = Vec::new();
        for (name, s) in &scenes {
            let (got, want) = (trained(&mut t, &[s]), predicted(&t, s));
            if verbose() {
                eprintln!("tracker, {what}, {name}: training loss {got:e}, prediction's error {want:e}");
            }
            close(&format!("{what}, {name}"), got, want);
            losses.push(got);
        }
        moved(&format!("{what}: the training loss from another scene's tokens"), losses[0], losses[1]);
        moved(&format!("{what}: the training loss from zero tokens"), losses[0], losses[2]);
        if token_positions {
            moved(&format!("{what}: the training loss from other token points"), losses[0], losses[3]);
        } else {
            unmoved(&format!("{what}: the training loss from other token points"), losses[0], losses[3]);
        }
        let batch = trained(&mut t, &[&scenes[0].1, &other]);
        close(
            &format!("{what}, a batch of two scenes"),
            batch,
            predicted(&t, &scenes[0].1) + predicted(&t, &other),
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Weight decay: which parameters of every real model decay.

/// Whether the project's rule (`params.rs`: tensors of two or more dimensions, weight
/// matrices and embeddings, decay; vectors, norm gains and biases, do not) decays a
/// parameter, found from its role by name; an error names a parameter of no known role, or
/// one whose shape does not fit its role.
fn decays_by_role(name: &str, shape: &[usize]) -> Result<bool, String> {
    let mut parts = name.rsplit('.');
    let (last, parent) = (parts.next().unwrap_or(""), parts.next());
    let (role, decays, matrix) = if last == "w" {
        ("a weight matrix", true, true)
    } else if last == "positions" {
        ("a learned embedding", true, true)
    } else if last == "b" {
        ("a bias", false, false)
    } else if last.contains("norm") {
        ("a norm gain", false, false)
    } else if parent == Some("table") {
        ("an adaLN modulation offset", false, false)
    } else {
        return Err(format!("{name} {shape:?}: a parameter of no known role (give it one here)"));
    };
    if matrix != (shape.len() >= 2) {
        return Err(format!("{name}: {role} of shape {shape:?}"));
    }
    Ok(decays)
}

/// The parameters among `infos` whose weight decay is not the rule's, each named with its
/// shape and what it got.
fn decay_offenders(infos: &[ParamInfo]) -> Vec<String> {
    infos
        .iter()
        .filter_map(|i| match decays_by_role(&i.name, &i.shape) {
            Ok(d) if d == i.decay => None,
            Ok(d) => Some(format!(
                "{} {:?} is {} but should {}",
                i.name,
                i.shape,
                if i.decay { "decayed" } else { "not decayed" },
                if d { "be" } else { "not be" }
            )),
            Err(e) => Some(e),
        })
        .collect()
}

#[track_caller]
fn assert_no_offenders(what: &str, offenders: &[String]) {
    assert!(
        offenders.is_empty(),
        "{what}: {} parameter(s) break the weight-decay rule: {}",
        offenders.len(),
        offenders.iter().take(8).cloned().collect::<Vec<_>>().join("; ")
    );
}

/// A built store decays what its declarations say: the decayed tensors lie in the flat
/// prefix AdamW decays and the others after it, and one AdamW step with zero gradients
/// (weight decay 0.5, rate 0.1: decayed values times 0.95, the others left alone) moves
/// exactly the tensors the rule decays.
fn check_store(what: &str, store: &mut ParamStore, declared: &ParamBuilder) {
    let gpu = store.flat_params().gpu().clone();
    let names = |infos: &[ParamInfo]| infos.iter().map(|i| (i.name.clone(), i.decay)).collect::<Vec<_>>();
    assert_eq!(names(store.infos()), names(declared.infos()), "{what}: the store against its declarations");
    let len = store.decay_len();
    let misplaced: Vec<String> = store
        .infos()
        .iter()
        .filter(|i| i.decay != (i.offset + i.numel <= len))
        .map(|i| {
            format!(
                "{} at {}..{} ({})",
                i.name,
                i.offset,
                i.offset + i.numel,
                if i.decay { "decayed" } else { "not decayed" }
            )
        })
        .collect();
    assert!(
        misplaced.is_empty(),
        "{what}: outside their side of the decayed prefix 0..{len}: {}",
        misplaced.join("; ")
    );
    randomize_params(store, 5, 1.0);
    let before: Vec<f32> = store.flat_params().read().unwrap();
    let mut rec = gpu.recorder().unwrap();
    store.zero_grads(&mut rec).unwrap();
    store
        .adamw_step(&mut rec, &AdamWConfig { weight_decay: 0.5, ..AdamWConfig::default() }, 0.1, None)
        .unwrap();
    rec.submit().unwrap();
    let after: Vec<f32> = store.flat_params().read().unwrap();
    let offenders: Vec<String> = store
        .infos()
        .iter()
        .filter_map(|i| {
            let r = i.offset..i.offset + i.numel;
            let decayed = before[r.clone()]
                .iter()
                .zip(&after[r.clone()])
                .all(|(&b, &a)| b != 0.0 && ((a as f64) - 0.95 * b as f64).abs() <= 1e-6 * (b as f64).abs());
            let kept = before[r.clone()].iter().zip(&after[r]).all(|(b, a)| a.to_bits() == b.to_bits());
            let want = decays_by_role(&i.name, &i.shape).unwrap_or(!i.decay);
            match (want, decayed, kept) {
                (true, true, _) | (false, _, true) => None,
                (true, ..) => Some(format!("{} {:?} did not decay", i.name, i.shape)),
                (false, ..) => Some(format!("{} {:?} moved (decayed?)", i.name, i.shape)),
            }
        })
        .collect();
    assert_no_offenders(&format!("{what}, one AdamW step"), &offenders);
}

/// Every real model at its tiny and paper configs (the paper's declared, not allocated, as
/// `velox config paper --params` counts them) decays its weight matrices and learned
/// embeddings and no norm gain, bias or adaLN offset, each parameter's role read from its
/// name; at the tiny configs the built store lays them out so and one AdamW step decays
/// exactly those. Would catch a norm gain, a bias or an offset table declared decayed (or a
/// matrix not), the rule in `params.rs` changed, or the store's decayed prefix laid out
/// wrong; the message names the parameter.
#[test]
fn weight_decay_falls_on_the_matrices_and_embeddings_of_every_model() {
    let gpu = gpu();
    let tracker_variants =
        |c: TrackerConfig| [c.clone(), TrackerConfig { token_positions: true, query_colour: true, ..c }];
    let mut declared: Vec<(String, ParamBuilder)> = Vec::new();
    for (name, cfg) in [("tiny", AutoencoderConfig::tiny()), ("paper", AutoencoderConfig::paper())] {
        declared.push((format!("autoencoder {name}"), Autoencoder::declare(&gpu, &cfg).unwrap()));
    }
    for (name, cfg) in [("tiny", VoxelConfig::tiny()), ("paper", VoxelConfig::paper())] {
        declared.push((format!("voxel decoder {name}"), VoxelDecoder::declare(&gpu, &cfg).unwrap()));
    }
    for (name, cfg) in [("tiny", TrackerConfig::tiny()), ("paper", TrackerConfig::paper())] {
        for (i, c) in tracker_variants(cfg).iter().enumerate() {
            declared.push((format!("tracker {name} (variant {i})"), Tracker::declare(&gpu, c).unwrap()));
        }
    }
    for (name, cfg) in [
        ("tiny", GeneratorConfig::tiny()),
        ("tiny with DINOv2", GeneratorConfig { dino_width: 12, ..GeneratorConfig::tiny() }),
        ("paper", GeneratorConfig::paper()),
    ] {
        declared.push((format!("generator {name}"), Generator::declare(&gpu, &cfg).unwrap()));
    }
    for (what, b) in &declared {
        assert_no_offenders(what, &decay_offenders(b.infos()));
        assert!(b.infos().iter().any(|i| i.decay) && b.infos().iter().any(|i| !i.decay), "{what}");
    }
    let find = |what: &str| &declared.iter().find(|(w, _)| w == what).unwrap().1;
    let mut ae = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 1).unwrap();
    check_store("autoencoder tiny", &mut ae.store, find("autoencoder tiny"));
    let mut vox = VoxelDecoder::new(&gpu, &VoxelConfig::tiny(), 1).unwrap();
    check_store("voxel decoder tiny", &mut vox.store, find("voxel decoder tiny"));
    let mut trk = Tracker::new(&gpu, &tracker_variants(TrackerConfig::tiny())[1], 1).unwrap();
    check_store("tracker tiny", &mut trk.store, find("tracker tiny (variant 1)"));
    let mut gen = Generator::new(&gpu, &GeneratorConfig::tiny(), 1).unwrap();
    check_store("generator tiny", &mut gen.store, find("generator tiny"));
}
