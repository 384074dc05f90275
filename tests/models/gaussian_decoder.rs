//! The Gaussian decoder at the tiny config: head activations against the f64 reference, the
//! backward pass against directional finite differences (parameters and tokens), occupied
//! voxels, bad inputs.

use crate::common;
use common::*;
use velox::engine::ops::gaussian_head::{head_forward, reference, HeadRange, RAW};
use velox::engine::ops::raster::{Gaussians, GAUSSIAN_WIDTHS};
use velox::models::config::AutoencoderConfig;
use velox::models::params::{build, ParamStore};
use velox::models::velox::gaussians::{occupied_voxels, GaussianDecoder};

fn setup(gpu: &Gpu) -> (ParamStore, GaussianDecoder, usize) {
    let c = AutoencoderConfig::tiny();
    let (dec, store) =
        build(gpu, 7, |p| GaussianDecoder::new(p, "gs", &c.gaussians, c.encoder.token_dim)).unwrap();
    // Larger weights in the head's last layer than the default init, so the finite difference
    // sees every output (the tiny config's head is an MLP, as the paper config's).
    let head = store.param("gs.head.fc2.w").unwrap();
    let n = head.numel();
    head.write(&Rng::new(70).normal_vec(n).iter().map(|v| v * 0.3).collect::<Vec<f32>>()).unwrap();
    (store, dec, c.encoder.token_dim)
}

fn centres(rng: &mut Rng, grid: usize, v: usize) -> Vec<f32> {
    let mut cloud = Vec::new();
    for _ in 0..v * 3 {
        cloud.extend([rng.range(-1.0, 1.0) as f32, rng.range(-1.0, 1.0) as f32, rng.range(-1.0, 1.0) as f32]);
        cloud.extend([0.5, 0.5, 0.5, 0.05]);
    }
    let c = occupied_voxels(&cloud, 0.05, grid);
    c[..3 * v.min(c.len() / 3)].to_vec()
}

fn weighted_sum(out: &Gaussians, w: &[Vec<f32>; 5]) -> f64 {
    out.fields()
        .iter()
        .zip(w)
        .map(|(t, w)| t.read::<f32>().unwrap().iter().zip(w).map(|(&a, &b)| a as f64 * b as f64).sum::<f64>())
        .sum()
}

#[test]
fn head_matches_reference() {
    let gpu = gpu();
    let mut rng = Rng::new(1);
    let range = HeadRange { offset_range: 0.05, scale_min: 0.001, scale_max: 0.01 };
    let (v, g) = (5, 3);
    let raw = rng.normal_vec(v * g * RAW).iter().map(|x| x * 3.0).collect::<Vec<f32>>();
    let c = rng.uniform_vec(v * 3, -1.0, 1.0);
    let traw = Tensor::from_slice(&gpu, &[v * g, RAW], &raw).unwrap();
    let tc = Tensor::from_slice(&gpu, &[v, 3], &c).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let out = head_forward(&mut rec, &traw, &tc, &range).unwrap();
    rec.submit().unwrap();
    let want = reference::head(&f64s(&raw), &f64s(&c), g, &range);
    for (t, w) in out.fields().iter().zip(&want) {
        assert_nmse("gaussian head", &t.read::<f32>().unwrap(), w, 1e-12);
    }
    let bad = Tensor::empty(&gpu, &[7, RAW], DType::F32).unwrap();
    let mut rec = gpu.recorder().unwrap();
    assert!(head_forward(&mut rec, &bad, &tc, &range).is_err());
}

#[test]
fn occupied_voxels_are_the_distinct_cells_of_one_frame() {
    let cloud = [
        0.01, 0.01, 0.01, 0.0, 0.0, 0.0, 0.02, // cell (4, 4, 4) of an 8-grid at tau 0.02
        0.2, 0.1, 0.05, 0.0, 0.0, 0.0, 0.02, // the same cell
        -1.0, 1.0, 0.99, 0.0, 0.0, 0.0, 0.02, // corner cells (0, 7, 7)
        0.5, 0.5, 0.5, 0.0, 0.0, 0.0, 0.03, // another frame
    ];
    let c = occupied_voxels(&cloud, 0.02, 8);
    assert_eq!(c, vec![-0.875, 0.875, 0.875, 0.125, 0.125, 0.125]);
}

#[test]
fn backward_matches_directional_finite_differences() {
    let gpu = gpu();
    let (store, dec, token_dim) = setup(&gpu);
    let mut rng = Rng::new(2);
    let c = centres(&mut rng, dec.cfg.grid, 12);
    let v = c.len() / 3;
    let tc = Tensor::from_slice(&gpu, &[v, 3], &c).unwrap();
    let k = 16;
    let s = rng.normal_vec(k * token_dim);
    let ts = Tensor::from_slice(&gpu, &[k, token_dim], &s).unwrap();
    let m = v * dec.cfg.gaussians_per_voxel;
    let w: [Vec<f32>; 5] = GAUSSIAN_WIDTHS.map(|c| rng.normal_vec(m * c));
    let d = Gaussians::from_fields(std::array::from_fn(|i| {
        let shape = if GAUSSIAN_WIDTHS[i] == 1 { vec![m] } else { vec![m, GAUSSIAN_WIDTHS[i]] };
        Tensor::from_slice(&gpu, &shape, &w[i]).unwrap()
    }));
    let mut rec = gpu.recorder().unwrap();
    store.zero_grads(&mut rec).unwrap();
    let (_, cache) = dec.forward(&mut rec, &ts, &tc, 0.05).unwrap();
    let d_tokens = dec.backward(&mut rec, &cache, &d).unwrap();
    rec.submit().unwrap();
    let grad: Vec<f32> = store.flat_grads().read().unwrap();
    let d_tokens: Vec<f32> = d_tokens.read().unwrap();
    let theta: Vec<f32> = store.flat_params().read().unwrap();

    let loss = |s: &[f32]| -> f64 {
        let ts = Tensor::from_slice(&gpu, &[k, token_dim], s).unwrap();
        let mut rec = gpu.recorder().unwrap();
        let (out, _) = dec.forward(&mut rec, &ts, &tc, 0.05).unwrap();
        rec.submit().unwrap();
        weighted_sum(&out, &w)
    };
    let check = |what: &str, analytic: f64, plus: f64, minus: f64, eps: f32| {
        let numeric = (plus - minus) / (2.0 * eps as f64);
        let rel = (numeric - analytic).abs() / analytic.abs().max(1e-6);
        if std::env::var_os("VELOX_TEST_VERBOSE").is_some() {
            eprintln!("gaussian decoder d/d{what}: analytic {analytic:.6e}, finite difference {numeric:.6e}, relative {rel:.2e}");
        }
        assert!(rel < 5e-3, "{what}: analytic {analytic} vs finite difference {numeric} ({rel:.2e})");
    };
    // Along a random direction over every parameter.
    let u = rng.normal_vec(theta.len());
    let eps = 2e-3f32;
    let at = |sign: f32| {
        store
            .flat_params()
            .write(&theta.iter().zip(&u).map(|(&t, &d)| t + sign * eps * d).collect::<Vec<f32>>())
            .unwrap();
        loss(&s)
    };
    let (plus, minus) = (at(1.0), at(-1.0));
    store.flat_params().write(&theta).unwrap();
    check("params", grad.iter().zip(&u).map(|(&a, &b)| a as f64 * b as f64).sum(), plus, minus, eps);
    // Every parameter together and each tensor alone, with every parameter randomised (the
    // head's enlarged last layer alone would leave the adaLN maps at their zero start). Would
    // catch any tensor's gradient wired wrong. A step of 1e-2: the f32 rounding of the 700-odd
    // outputs puts a floor near 3e-4 under a derivative at 3e-3. Measured: within 1 % where the
    // derivative exceeds 1e-2, within 2e-4 for the self-attention's queries and keys (2e-3).
    randomize_params(&store, 18, 0.6);
    let theta_r: Vec<f32> = store.flat_params().read().unwrap();
    let mut rec = gpu.recorder().unwrap();
    store.zero_grads(&mut rec).unwrap();
    let (_, cache_r) = dec.forward(&mut rec, &ts, &tc, 0.05).unwrap();
    dec.backward(&mut rec, &cache_r, &d).unwrap();
    rec.submit().unwrap();
    let grad_r: Vec<f32> = store.flat_grads().read().unwrap();
    let mut groups = vec![ParamGroup::under(&store, "")];
    groups.extend(ParamGroup::each(&store));
    let mut at = |p: &[f32]| {
        store.flat_params().write(p).unwrap();
        loss(&s)
    };
    let worst = check_directional(
        "gaussian decoder",
        &theta_r,
        &grad_r,
        &groups,
        (1, 1),
        1e-2,
        (2e-2, 2e-4),
        &mut Rng::new(17),
        &mut at,
    );
    if verbose() {
        eprintln!("gaussian decoder: worst relative error {worst:.2e}");
    }
    store.flat_params().write(&theta).unwrap();
    // Along a random direction over the tokens.
    let u = rng.normal_vec(s.len());
    let shifted = |sign: f32| s.iter().zip(&u).map(|(&a, &b)| a + sign * eps * b).collect::<Vec<f32>>();
    let analytic = d_tokens.iter().zip(&u).map(|(&a, &b)| a as f64 * b as f64).sum();
    check("tokens", analytic, loss(&shifted(1.0)), loss(&shifted(-1.0)), eps);
}

#[test]
fn bad_inputs_get_clear_errors() {
    let gpu = gpu();
    let (_store, dec, token_dim) = setup(&gpu);
    let s = Tensor::empty(&gpu, &[4, token_dim], DType::F32).unwrap();
    let c = Tensor::from_slice(&gpu, &[1, 3], &[0.0f32; 3]).unwrap();
    let mut rec = gpu.recorder().unwrap();
    let err =
        dec.forward(&mut rec, &s, &Tensor::empty(&gpu, &[0, 3], DType::F32).unwrap(), 0.0).err().unwrap();
    assert!(err.to_string().contains("centres"), "{err}");
    assert!(dec.forward(&mut rec, &s, &c, f32::NAN).is_err());
    assert!(dec
        .forward(&mut rec, &Tensor::empty(&gpu, &[4, token_dim + 1], DType::F32).unwrap(), &c, 0.0)
        .is_err());
}

#[test]
fn the_paper_config_counts_the_papers_parameters() {
    use velox::models::config::AutoencoderConfig;
    use velox::models::params::declare;
    // The paper's Gaussian decoder has 75.8 M parameters; its head "expanded by an MLP" and a
    // two-layer input reach that, a single linear head and input 73.1 M.
    let count = |cfg: &velox::models::config::GaussianConfig| {
        let b = declare(&gpu(), |p| GaussianDecoder::new(p, "g", cfg, 32)).unwrap();
        b.num_parameters() as f64 / 1e6
    };
    let paper = AutoencoderConfig::paper().gaussians;
    let with = count(&paper);
    let without = count(&velox::models::config::GaussianConfig { input_hidden: 0, head_hidden: 0, ..paper });
    assert!((with - 75.8).abs() < 0.1, "paper config: {with:.2} M");
    assert!((without - 73.1).abs() < 0.1, "single linear head and input: {without:.2} M");
}
