//! The Velox encoder at the tiny config: shapes, determinism, its backward pass against
//! finite differences per tensor, and bad clouds.

use crate::common;
use common::*;
use velox::io::cloud;
use velox::models::config::{AutoencoderConfig, EncoderConfig};
use velox::models::params::{build, ParamStore};
use velox::models::velox::encoder::Encoder;

/// A random cloud of `n` points over 24 frames.
fn random_cloud(rng: &mut Rng, n: usize) -> Vec<f32> {
    let mut c = Vec::with_capacity(n * 7);
    for _ in 0..n {
        for _ in 0..3 {
            c.push(rng.range(-1.0, 1.0) as f32);
        }
        for _ in 0..3 {
            c.push(rng.uniform() as f32);
        }
        c.push(rng.below(24) as f32 / 100.0);
    }
    c
}

fn setup(gpu: &Gpu) -> (ParamStore, Encoder) {
    setup_with(gpu, AutoencoderConfig::tiny().encoder)
}

fn setup_with(gpu: &Gpu, cfg: EncoderConfig) -> (ParamStore, Encoder) {
    let (enc, store) = build(gpu, 5, |p| Encoder::new(p, "enc", &cfg)).unwrap();
    (store, enc)
}

/// sum(s * g) for the encoder's tokens, with the queries drawn from `seed`.
fn loss(gpu: &Gpu, enc: &Encoder, cloud: &Tensor, g: &[f32], seed: u64) -> f64 {
    let mut rec = gpu.recorder().unwrap();
    let (s, _) = enc.forward(&mut rec, cloud, &mut Rng::new(seed)).unwrap();
    rec.submit().unwrap();
    s.read::<f32>().unwrap().iter().zip(g).map(|(&a, &b)| a as f64 * b as f64).sum()
}

#[test]
fn tokens_are_finite_deterministic_and_shaped() {
    let gpu = gpu();
    let (_store, enc) = setup(&gpu);
    let mut rng = Rng::new(1);
    let data = random_cloud(&mut rng, 500);
    let t = cloud::upload(&gpu, &data).unwrap();
    let run = || {
        let mut rec = gpu.recorder().unwrap();
        let (s, _) = enc.forward(&mut rec, &t, &mut Rng::new(9)).unwrap();
        rec.submit().unwrap();
        (s.shape().to_vec(), s.read::<f32>().unwrap())
    };
    let (shape, a) = run();
    let (_, b) = run();
    assert_eq!(shape, [enc.cfg.tokens, enc.cfg.token_dim]);
    assert!(a.iter().all(|v| v.is_finite()));
    assert_eq!(a, b, "same cloud, same seed: same tokens");
    assert!(a.iter().map(|v| v * v).sum::<f32>() > 1e-3, "tokens are not all zero");
}

/// The backward pass against central differences of `sum(tokens * g)`, along directions over
/// every parameter and over each tensor alone, with the parameters randomised so that no
/// layer's small start hides the ones before it. Would catch any tensor's gradient wired
/// wrong (the queries' and the cloud's paths through cross-attention included).
#[test]
fn backward_matches_central_differences_per_tensor() {
    let gpu = gpu();
    // Windows of a quarter of the box and of 24 frames, so that a window holds several of the
    // 32 queries: with the tiny config's windows most hold one, and the self-attention's
    // queries and keys would have no gradient to check.
    let cfg = EncoderConfig { window: [1.0, 1.0, 1.0, 0.24], ..AutoencoderConfig::tiny().encoder };
    let (store, enc) = setup_with(&gpu, cfg);
    randomize_params(&store, 14, 0.6);
    let mut rng = Rng::new(2);
    let data = random_cloud(&mut rng, 300);
    let cloud = cloud::upload(&gpu, &data).unwrap();
    let g = rng.normal_vec(enc.cfg.tokens * enc.cfg.token_dim);
    let tg = Tensor::from_slice(&gpu, &[enc.cfg.tokens, enc.cfg.token_dim], &g).unwrap();

    let mut rec = gpu.recorder().unwrap();
    store.zero_grads(&mut rec).unwrap();
    let (_, cache) = enc.forward(&mut rec, &cloud, &mut Rng::new(3)).unwrap();
    enc.backward(&mut rec, &cache, &tg).unwrap();
    rec.submit().unwrap();
    let grad: Vec<f32> = store.flat_grads().read().unwrap();
    let theta: Vec<f32> = store.flat_params().read().unwrap();
    let mut groups = vec![ParamGroup::under(&store, "")];
    groups.extend(ParamGroup::each(&store));
    let mut at = |p: &[f32]| {
        store.flat_params().write(p).unwrap();
        loss(&gpu, &enc, &cloud, &g, 3)
    };
    let worst =
        check_directional("encoder", &theta, &grad, &groups, (1, 1), 1e-2, (1e-2, 5e-5), &mut rng, &mut at);
    if verbose() {
        eprintln!("encoder: worst relative error {worst:.2e}");
    }
}

#[test]
fn bad_clouds_get_clear_errors() {
    let gpu = gpu();
    let (_store, enc) = setup(&gpu);
    let mut rng = Rng::new(4);
    // Fewer points than tokens.
    let few = cloud::upload(&gpu, &random_cloud(&mut rng, enc.cfg.tokens - 1)).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let err = enc.forward(&mut rec, &few, &mut Rng::new(1)).err().unwrap().to_string();
    assert!(err.contains("at least"), "{err}");
    // Wrong channel count.
    let six = Tensor::empty(&gpu, &[100, 6], DType::F32).unwrap();
    let err = enc.forward(&mut rec, &six, &mut Rng::new(1)).err().unwrap().to_string();
    assert!(err.contains("[N, 7]"), "{err}");
    // NaN and out-of-bounds points are refused before upload.
    let mut bad = random_cloud(&mut rng, 50);
    bad[7 * 10 + 1] = f32::NAN;
    assert!(cloud::upload(&gpu, &bad).unwrap_err().to_string().contains("point 10"));
    bad[7 * 10 + 1] = 3.0;
    assert!(cloud::upload(&gpu, &bad).unwrap_err().to_string().contains("outside"));
    assert!(cloud::upload(&gpu, &[]).unwrap_err().to_string().contains("empty"));
}

#[test]
fn a_batch_encodes_each_cloud_as_alone() {
    // Three clouds of different sizes in one batch: every cloud's tokens equal those it gets
    // alone with the same generator, and the batch's parameter gradients equal the sum of the
    // three alone (to summation order: the products over all points sum in another order).
    let gpu = gpu();
    let (store, enc) = setup(&gpu);
    let mut rng = Rng::new(4);
    let clouds: Vec<Tensor> =
        [300, 517, 260].iter().map(|&n| cloud::upload(&gpu, &random_cloud(&mut rng, n)).unwrap()).collect();
    let (k, d) = (enc.cfg.tokens, enc.cfg.token_dim);
    let g: Vec<Vec<f32>> = (0..3).map(|_| rng.normal_vec(k * d)).collect();
    let rngs = || (0..3).map(|i| Rng::new(40 + i)).collect::<Vec<_>>();

    let mut alone_tokens = Vec::new();
    let mut alone_grads = vec![0f64; store.flat_grads().numel()];
    for (i, (c, mut r)) in clouds.iter().zip(rngs()).enumerate() {
        let mut rec = gpu.recorder().unwrap();
        store.zero_grads(&mut rec).unwrap();
        let (s, cache) = enc.forward(&mut rec, c, &mut r).unwrap();
        let tg = Tensor::from_slice(&gpu, &[k, d], &g[i]).unwrap();
        enc.backward(&mut rec, &cache, &tg).unwrap();
        rec.submit().unwrap();
        alone_tokens.extend(s.read::<f32>().unwrap());
        for (a, v) in alone_grads.iter_mut().zip(store.flat_grads().read::<f32>().unwrap()) {
            *a += v as f64;
        }
    }

    let mut rec = gpu.recorder().unwrap();
    store.zero_grads(&mut rec).unwrap();
    let refs: Vec<&Tensor> = clouds.iter().collect();
    let (s, cache) = enc.forward_batch(&mut rec, &refs, &mut rngs()).unwrap();
    assert_eq!(cache.layout.batch, 3);
    let tg = Tensor::from_slice(&gpu, &[3 * k, d], &g.concat()).unwrap();
    enc.backward(&mut rec, &cache, &tg).unwrap();
    rec.submit().unwrap();
    assert_eq!(s.shape(), [3 * k, d]);
    let batch_tokens: Vec<f32> = s.read().unwrap();
    assert_nmse("batch tokens", &batch_tokens, &f64s(&alone_tokens), 1e-12);
    let batch_grads: Vec<f32> = store.flat_grads().read().unwrap();
    assert_nmse("batch gradients", &batch_grads, &alone_grads, 1e-12);

    // A batch needs one generator per cloud.
    let mut rec = gpu.recorder().unwrap();
    let err = enc.forward_batch(&mut rec, &refs, &mut rngs()[..2]).err().unwrap().to_string();
    assert!(err.contains("one generator per cloud"), "{err}");
}
