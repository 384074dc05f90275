//! The generator (DiT) at the tiny config: its backward pass against a directional finite
//! difference (condition dropout on and off), a batch against its scenes alone, the null
//! condition ignoring the video, sampling with keys and values computed once against the
//! training forward, that it learns to tell two scenes apart by their videos, that f16 training
//! (through the trainer, with its loss scale) follows f32, and the paper config's parameter
//! count.

use crate::common;
use common::*;
use velox::models::config::GeneratorConfig;
use velox::models::train::Trainable;
use velox::models::velox::dinov2::PATCH_VALUES;
use velox::models::velox::generator::{Condition, GenSample, GenerateSpec, Generator};
use velox::models::velox::surface::Sampler;

/// A scene: random tokens and random patches (the video), from `seed`.
fn sample(gpu: &Gpu, cfg: &GeneratorConfig, seed: u64) -> GenSample {
    let mut rng = Rng::new(seed);
    let tokens = rng.normal_vec(cfg.tokens * cfg.token_dim);
    let patches = rng.normal_vec(cfg.cond_tokens() * PATCH_VALUES);
    let dino = (cfg.dino_width > 0).then(|| {
        Tensor::from_slice(
            gpu,
            &[cfg.cond_tokens(), cfg.dino_width],
            &rng.normal_vec(cfg.cond_tokens() * cfg.dino_width),
        )
        .unwrap()
    });
    GenSample {
        tokens: Tensor::from_slice(gpu, &[cfg.tokens, cfg.token_dim], &tokens).unwrap(),
        condition: Condition {
            patches: Tensor::from_slice(gpu, &[cfg.cond_tokens(), PATCH_VALUES], &patches).unwrap(),
            dino,
        },
    }
}

fn zero(gpu: &Gpu, g: &Generator) {
    let mut rec = gpu.recorder().unwrap();
    g.store.zero_grads(&mut rec).unwrap();
    rec.submit().unwrap();
}

/// Every parameter drawn at random, so that the zero-initialised gates, tables and output
/// projections pass gradients too. (The flat buffer, padding between parameters included: its
/// length depends on the device's offset alignment.)
fn randomise(g: &Generator, seed: u64) {
    let n = g.store.flat_params().numel();
    let theta: Vec<f32> = Rng::new(seed).normal_vec(n).iter().map(|v| 0.2 * v).collect();
    g.store.flat_params().write(&theta).unwrap();
}

#[test]
fn backward_matches_a_directional_finite_difference() {
    let gpu = gpu();
    for (dropout, dino) in [(0.0, 0), (0.5, 12)] {
        let cfg = GeneratorConfig { cond_dropout: dropout, dino_width: dino, ..GeneratorConfig::tiny() };
        let mut g = Generator::new(&gpu, &cfg, 2).unwrap();
        randomise(&g, 3);
        let s = [sample(&gpu, &cfg, 4), sample(&gpu, &cfg, 5)];
        let refs = [&s[0], &s[1]];
        // Seeds 9 and 10 drop the first scene's condition and keep the second's at 0.5.
        let rngs = || vec![Rng::new(9), Rng::new(10)];
        zero(&gpu, &g);
        let l0 = g.accumulate(&refs, &mut rngs(), 1.0).unwrap();
        assert!(l0.total() > 0.0, "{l0:?}");
        let grad: Vec<f32> = g.store.flat_grads().read().unwrap();
        let theta: Vec<f32> = g.store.flat_params().read().unwrap();
        // Every parameter together (measured within 9e-4), and in the run that has them all
        // (the DINOv2 path, a dropped condition) each part alone (a block, the adaLN maps, the
        // time embedding...): the loss is large with every parameter randomised, and its f32
        // rounding (about 1e-3 in a derivative at these steps) would swamp a small tensor alone:
        // measured up to 3.5e-4 off in absolute terms in every part, whichever the kernels'
        // summation order (the positions' 2e-2: 4e-5 off with the GPU variants, 2.8e-4 with
        // the CPU ones), so a part's slope is held to that floor.
        let mut groups = vec![ParamGroup::under(&g.store, "")];
        if dino > 0 {
            let mut parts: Vec<String> = Vec::new();
            for info in g.store.infos() {
                let mut it = info.name.split('.');
                let first = it.next().unwrap();
                let part = match (first, it.next()) {
                    ("blocks", Some(i)) => format!("blocks.{i}."),
                    (_, Some(_)) => format!("{first}."),
                    (_, None) => first.to_string(),
                };
                if !parts.contains(&part) {
                    parts.push(part);
                }
            }
            groups.extend(parts.iter().map(|p| ParamGroup::under(&g.store, p)));
        }
        let what = format!("dropout {dropout}, dino {dino}");
        let mut at = |p: &[f32]| {
            g.store.flat_params().write(p).unwrap();
            g.accumulate(&refs, &mut rngs(), 1.0).unwrap().total()
        };
        let worst = check_directional(
            &what,
            &theta,
            &grad,
            &groups,
            (1, 1),
            1e-3,
            (2e-3, 5e-4),
            &mut Rng::new(5),
            &mut at,
        );
        if verbose() {
            eprintln!("{what}: worst relative error {worst:.2e}");
        }
        // Each part of the model has a gradient: the RGB embedding only through kept scenes.
        for name in
            ["rgb.w", "cond.w", "positions", "blocks.1.table.gate_mlp", "adaln.scale_attn.w", "time.fc1.w"]
        {
            g.store.flat_params().write(&theta).unwrap();
            let grad: Vec<f32> = g.store.grad(name).unwrap().read().unwrap();
            assert!(grad.iter().any(|&v| v != 0.0), "{name} has no gradient");
        }
    }
}

#[test]
fn a_batch_gives_the_sum_of_its_scenes_gradients() {
    let gpu = gpu();
    let cfg = GeneratorConfig { cond_dropout: 0.5, ..GeneratorConfig::tiny() };
    let mut g = Generator::new(&gpu, &cfg, 1).unwrap();
    randomise(&g, 7);
    let samples: Vec<GenSample> = (0..3).map(|i| sample(&gpu, &cfg, 30 + i)).collect();
    let refs: Vec<&GenSample> = samples.iter().collect();
    let rngs = || (0..3).map(|i| Rng::new(20 + i)).collect::<Vec<_>>();
    zero(&gpu, &g);
    let batch = g.accumulate(&refs, &mut rngs(), 1.0 / 3.0).unwrap();
    let batch_grads: Vec<f32> = g.store.flat_grads().read().unwrap();
    zero(&gpu, &g);
    let mut total = 0.0;
    for (s, mut r) in refs.iter().zip(rngs()) {
        total += g.accumulate(&[s], std::slice::from_mut(&mut r), 1.0 / 3.0).unwrap().total();
    }
    let single: Vec<f32> = g.store.flat_grads().read().unwrap();
    assert_nmse("batch-3 gradient against three batch-1 gradients", &batch_grads, &f64s(&single), 1e-10);
    assert!((batch.total() - total).abs() <= 1e-5 * total, "batch {} against singles {total}", batch.total());
}

fn spec(steps: usize, guidance: f32) -> GenerateSpec {
    GenerateSpec { steps, sampler: Sampler::Euler, guidance, seed: 11, precision: Precision::F32 }
}

/// One Euler step from `t = 0` is `x_1 = eps + v(eps, 0)`: as the training loss's target at
/// `t = 0` is `u = x - eps`, a scene whose tokens are that `x_1` has (nearly) zero loss there.
/// Checks that sampling, with its keys and values computed once, runs the network training does.
#[test]
fn sampling_runs_the_network_that_training_runs() {
    let gpu = gpu();
    let cfg = GeneratorConfig::tiny();
    let g = Generator::new(&gpu, &cfg, 4).unwrap();
    randomise(&g, 8);
    let s = sample(&gpu, &cfg, 40);
    let x1 = g.generate(&s.condition, &spec(1, 1.0)).unwrap();
    let eps = Rng::new(11).normal_vec(cfg.tokens * cfg.token_dim);
    let loss_at = |tokens: &Tensor| {
        let scene = GenSample {
            tokens: tokens.clone(),
            condition: Condition { patches: s.condition.patches.clone(), dino: None },
        };
        let mut rec = gpu.recorder().unwrap();
        let (loss, _, _) = g.flow_loss(&mut rec, &[&scene], &eps, &[0.0], &[true], 1.0).unwrap();
        rec.submit().unwrap();
        loss.read::<f32>().unwrap()[0] as f64
    };
    let on = loss_at(&x1);
    let off = loss_at(&s.tokens);
    assert!(on < 1e-10 * off.max(1.0) + 1e-10, "loss at the sampled tokens {on}, elsewhere {off}");

    // Guidance 0 is the null condition alone: the video does not matter.
    let other = sample(&gpu, &cfg, 41);
    let null_a: Vec<f32> = g.generate(&s.condition, &spec(3, 0.0)).unwrap().read().unwrap();
    let null_b: Vec<f32> = g.generate(&other.condition, &spec(3, 0.0)).unwrap().read().unwrap();
    assert_nmse("null condition, two videos", &null_a, &f64s(&null_b), 1e-12);
    // The condition does matter, and guidance moves the result.
    let cond_a: Vec<f32> = g.generate(&s.condition, &spec(3, 1.0)).unwrap().read().unwrap();
    let cond_b: Vec<f32> = g.generate(&other.condition, &spec(3, 1.0)).unwrap().read().unwrap();
    assert!(nmse(&cond_a, &f64s(&cond_b)) > 1e-6);
    let guided: Vec<f32> = g.generate(&s.condition, &spec(3, 3.0)).unwrap().read().unwrap();
    assert!(nmse(&guided, &f64s(&cond_a)) > 1e-6);
    // Bad requests are refused by name.
    assert!(g.generate(&s.condition, &spec(0, 1.0)).unwrap_err().to_string().contains("step"));
    assert!(g.generate(&s.condition, &spec(2, f32::NAN)).unwrap_err().to_string().contains("guidance"));
    let wrong = Condition {
        patches: Tensor::from_slice(&gpu, &[3, PATCH_VALUES], &vec![0.0; 3 * PATCH_VALUES]).unwrap(),
        dino: None,
    };
    assert!(g.generate(&wrong, &spec(2, 1.0)).unwrap_err().to_string().contains("patches"));
}

/// Two scenes with different videos: trained on both, the generator makes from each video
/// tokens nearer to that scene's than to the other's.
#[test]
fn it_learns_which_video_shows_which_scene() {
    let gpu = gpu();
    // Measured: 300 steps with warmup 10 left both scenes at NMSE 1.3 to 1.8 (the decaying rate
    // falls too soon); warmup 100 brings them to 0.25 and 0.34, against 2.2 to the other's.
    let cfg = GeneratorConfig { cond_dropout: 0.1, warmup: 100, ..GeneratorConfig::tiny() };
    let mut g = Generator::new(&gpu, &cfg, 6).unwrap();
    let scenes = [sample(&gpu, &cfg, 50), sample(&gpu, &cfg, 51)];
    let refs = [&scenes[0], &scenes[1]];
    for step in 1..=300u64 {
        zero(&gpu, &g);
        let mut rngs = vec![Rng::new(1000 + 2 * step), Rng::new(1001 + 2 * step)];
        let l = g.accumulate(&refs, &mut rngs, 0.5).unwrap().total();
        if step % 50 == 0 && std::env::var_os("VELOX_TEST_VERBOSE").is_some() {
            eprintln!("step {step}: loss {l:.4}");
        }
        let (lr, adamw) = (g.optimisation().learning_rate(step), g.adamw);
        let mut rec = gpu.recorder().unwrap();
        g.store.adamw_step(&mut rec, &adamw, lr, Some(1.0)).unwrap();
        rec.submit().unwrap();
    }
    let truth: Vec<Vec<f32>> = scenes.iter().map(|s| s.tokens.read().unwrap()).collect();
    for (i, s) in scenes.iter().enumerate() {
        let made: Vec<f32> = g.generate(&s.condition, &spec(10, 2.0)).unwrap().read().unwrap();
        let own = nmse(&made, &f64s(&truth[i]));
        let other = nmse(&made, &f64s(&truth[1 - i]));
        if std::env::var_os("VELOX_TEST_VERBOSE").is_some() {
            eprintln!("scene {i}: NMSE to its own tokens {own:.3}, to the other's {other:.3}");
        }
        assert!(
            own < 0.3 * other && own < 0.6,
            "scene {i}: NMSE to its own tokens {own}, to the other's {other}"
        );
    }
}

/// Would catch: a generator step recorded while the last runs that differs from one recorded
/// after it.
#[test]
fn steps_recorded_ahead_are_the_same_steps() {
    let gpu = gpu();
    let cfg = GeneratorConfig::tiny();
    let scenes = [sample(&gpu, &cfg, 60), sample(&gpu, &cfg, 61)];
    recorded_ahead_is_the_same(|| Generator::new(&gpu, &cfg, 7).unwrap(), &[&scenes[0], &scenes[1]], 4);
}

#[test]
fn f16_training_follows_f32() {
    // The adaLN-single DiT with cross-attention to the condition, trained by the library
    // trainer 60 steps on two scenes from the same start in f32 and in f16 (f16 operands of
    // every product forward and backward, f32 masters, the loss scaled by 2^16).
    let gpu = gpu();
    let cfg = GeneratorConfig { warmup: 20, ..GeneratorConfig::tiny() };
    let scenes = [sample(&gpu, &cfg, 60), sample(&gpu, &cfg, 61)];
    let losses = |precision| {
        let mut g = Generator::new(&gpu, &cfg, 7).unwrap();
        trainer_losses(&mut g, &[&scenes[0], &scenes[1]], 60, precision)
    };
    let (full, half) = (losses(Precision::F32), losses(Precision::F16));
    let (worst, mean) = relative_gaps(&full, &half);
    eprintln!(
        "generator f16 against f32, 60 steps: loss {:.4} -> {:.4} (f32 {:.4} -> {:.4}); relative difference \
         at most {worst:.2e}, mean {mean:.2e}",
        half[0], half[59], full[0], full[59]
    );
    assert!(worst < 0.02 && mean < 2e-3, "f16 strays from f32: worst {worst:.3e}, mean {mean:.3e}");
    // Measured on lavapipe: at most 7.9e-3, mean 7.8e-4; the flow loss 1.82 -> 1.67 (noisy: each
    // step draws its own flow times). The untrained network's output is zero (adaLN-Zero), the
    // trivial model of a regression whose targets have mean zero, so the first steps' loss is
    // the trivial model's: both runs must end 5 % under it on the means of 20 steps.
    for (what, run) in [("f32", &full), ("f16", &half)] {
        let (start, end) = (mean_of(&run[..20]), mean_of(&run[40..]));
        assert!(end < 0.95 * start, "the {what} run must learn: {start} -> {end}");
    }
}

#[test]
fn the_paper_config_has_the_papers_size() {
    let n = Generator::declare(&gpu(), &GeneratorConfig::paper()).unwrap().num_parameters();
    eprintln!("generator paper config: {n} parameters (paper: 623 M)");
    assert!((n as f64 - 623e6).abs() < 0.05 * 623e6, "{n}");
}
