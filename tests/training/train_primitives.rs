//! Training primitives on lavapipe: fused AdamW and the global gradient norm against their f64
//! references, NaN detection, the noam schedule, the parameter store, safetensors checkpoints
//! (round trip, corrupt files, interrupted writes), and a small quadratic minimised end to end.

use crate::common;
use common::*;
use velox::engine::ops::adamw::{self, adamw, adamw_chunked, AdamWConfig, AdamWStep, AdamWTensors};
use velox::engine::ops::binary::{binary_into, Binary};
use velox::engine::ops::norm::{self, check_finite, global_norm, global_norm_chunked, NormScratch};
use velox::engine::ops::unary::{unary_into, Unary};
use velox::engine::FileOp;
use velox::models::checkpoint::{self, temp_path};
use velox::models::params::{Init, ParamStore};
use velox::models::schedule::{noam, Noam};

/// More than 65535 workgroups of 256: the AdamW dispatch must fold into two dimensions.
const HUGE: usize = 65_536 * 256 + 3;

fn f32_tensor(gpu: &Gpu, x: &[f32]) -> Tensor {
    Tensor::from_slice(gpu, &[x.len()], x).unwrap()
}

/// Runs `steps` AdamW steps on the GPU and in f64 with fresh random gradients each step and
/// returns the NMSE of (params, m, v).
fn adamw_case(n: usize, decay_len: usize, max_norm: Option<f64>, use_norm: bool, steps: u64) -> [f64; 3] {
    let gpu = gpu();
    let mut rng = Rng::new(n as u64 * 31 + decay_len as u64);
    let p0 = rng.normal_vec(n);
    let (p, m, v) = (f32_tensor(&gpu, &p0), f32_tensor(&gpu, &vec![0.0; n]), f32_tensor(&gpu, &vec![0.0; n]));
    let (mut rp, mut rm, mut rv) = (f64s(&p0), vec![0f64; n], vec![0f64; n]);
    let cfg = AdamWConfig { weight_decay: 0.1, ..AdamWConfig::default() };
    let scratch = NormScratch::new(&gpu, n).unwrap();
    for step in 1..=steps {
        let g: Vec<f32> = rng.normal_vec(n).iter().map(|x| x * 0.5).collect();
        let gt = f32_tensor(&gpu, &g);
        let s = AdamWStep { lr: 1e-2 / step as f64, step, grad_scale: 0.75, max_norm };
        let mut rec = gpu.recorder().unwrap();
        let norm = if use_norm {
            norm::global_norm_into(&mut rec, &gt, &scratch).unwrap();
            Some(scratch.result())
        } else {
            None
        };
        let t = AdamWTensors { params: &p, grads: &gt, m: &m, v: &v, decay_len, norm };
        adamw(&mut rec, &t, &cfg, &s).unwrap();
        rec.submit().unwrap();
        let rnorm = use_norm.then(|| norm::reference::global_norm(&g));
        assert!(adamw::reference::adamw(&mut rp, &mut rm, &mut rv, &g, decay_len, rnorm, &cfg, &s));
    }
    let e = [
        nmse(&p.read::<f32>().unwrap(), &rp),
        nmse(&m.read::<f32>().unwrap(), &rm),
        nmse(&v.read::<f32>().unwrap(), &rv),
    ];
    eprintln!("adamw n={n} decay_len={decay_len} max_norm={max_norm:?} norm={use_norm}: nmse p {:.2e} m {:.2e} v {:.2e}", e[0], e[1], e[2]);
    e
}

#[test]
fn adamw_matches_reference_with_and_without_decay_and_clipping() {
    for n in [1, 257, 10_007] {
        // (decay_len, max_norm, read the norm): no decay, no clip; all decay; half decay with
        // clipping active (the norm is about 0.4 sqrt(n) > 0.05); clipping inactive (bound far
        // above the norm).
        for (decay_len, max_norm, use_norm) in [
            (0, None, false),
            (n, None, false),
            (n / 2, Some(0.05), true),
            (n / 3, Some(1e6), true),
            (n, None, true),
        ] {
            let e = adamw_case(n, decay_len, max_norm, use_norm, 5);
            for (what, err) in ["params", "m", "v"].iter().zip(e) {
                assert!(
                    err < 1e-11,
                    "adamw n={n} decay {decay_len} clip {max_norm:?}: {what} nmse {err:.2e}"
                );
            }
        }
    }
}

#[test]
fn clipping_scales_the_step_when_active() {
    // With a bound far below the norm, the effective gradient is the clipped one: compare with the
    // reference given the unclipped gradient times the clip factor and no clipping.
    let gpu = gpu();
    let n = 1000;
    let mut rng = Rng::new(9);
    let g = rng.normal_vec(n);
    let gt = f32_tensor(&gpu, &g);
    let p = f32_tensor(&gpu, &vec![1.0; n]);
    let (m, v) = (f32_tensor(&gpu, &vec![0.0; n]), f32_tensor(&gpu, &vec![0.0; n]));
    let cfg = AdamWConfig { weight_decay: 0.0, ..AdamWConfig::default() };
    let mut rec = gpu.recorder().unwrap();
    let nt = global_norm(&mut rec, &gt).unwrap();
    let s = AdamWStep { lr: 0.1, step: 1, grad_scale: 1.0, max_norm: Some(0.5) };
    adamw(
        &mut rec,
        &AdamWTensors { params: &p, grads: &gt, m: &m, v: &v, decay_len: 0, norm: Some(&nt) },
        &cfg,
        &s,
    )
    .unwrap();
    rec.submit().unwrap();
    let norm = norm::reference::global_norm(&g);
    let clip = 0.5 / (norm + 1e-6);
    let want: Vec<f64> = g.iter().map(|&x| (1.0 - cfg.beta1) * x as f64 * clip).collect();
    assert_nmse("first moment after a clipped step", &m.read::<f32>().unwrap(), &want, 1e-12);
    let clipped_norm = m.read::<f32>().unwrap().iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
    assert!((clipped_norm / (1.0 - cfg.beta1) - 0.5).abs() < 1e-5, "clipped gradient norm {clipped_norm}");
}

#[test]
fn adamw_in_chunks_and_past_one_dispatch_dimension() {
    let gpu = gpu();
    let n = 10_007;
    let mut rng = Rng::new(11);
    let p0 = rng.normal_vec(n);
    let g = rng.normal_vec(n);
    let cfg = AdamWConfig::default();
    let s = AdamWStep { lr: 1e-3, step: 3, grad_scale: 1.0, max_norm: Some(1.0) };
    let run = |chunk: Option<usize>| {
        let (p, gt) = (f32_tensor(&gpu, &p0), f32_tensor(&gpu, &g));
        let (m, v) = (f32_tensor(&gpu, &g), f32_tensor(&gpu, &p0.iter().map(|x| x * x).collect::<Vec<_>>()));
        let chunk = chunk.map(|c| c * p.view_alignment());
        let mut rec = gpu.recorder().unwrap();
        let scratch = match chunk {
            Some(c) => {
                let scratch = NormScratch::for_chunks(&gpu, n, c).unwrap();
                global_norm_chunked(&mut rec, &gt, &scratch, c).unwrap();
                scratch
            }
            None => {
                let scratch = NormScratch::new(&gpu, n).unwrap();
                norm::global_norm_into(&mut rec, &gt, &scratch).unwrap();
                scratch
            }
        };
        let t = AdamWTensors {
            params: &p,
            grads: &gt,
            m: &m,
            v: &v,
            decay_len: 5000,
            norm: Some(scratch.result()),
        };
        match chunk {
            Some(c) => adamw_chunked(&mut rec, &t, &cfg, &s, c).unwrap(),
            None => adamw(&mut rec, &t, &cfg, &s).unwrap(),
        }
        rec.submit().unwrap();
        (p.read::<f32>().unwrap(), m.read::<f32>().unwrap(), v.read::<f32>().unwrap())
    };
    let whole = run(None);
    // Chunk lengths that do and do not divide the decay boundary (5000).
    for c in [100, 333] {
        let parts = run(Some(c));
        // The norm's partial sums group differently, so the clip factor may differ in its last bit.
        assert_nmse(&format!("chunks of {c} x align: params"), &parts.0, &f64s(&whole.0), 1e-13);
        assert_nmse(&format!("chunks of {c} x align: m"), &parts.1, &f64s(&whole.1), 1e-13);
        assert_nmse(&format!("chunks of {c} x align: v"), &parts.2, &f64s(&whole.2), 1e-13);
    }

    // One step over more workgroups than one dispatch dimension allows, with moments starting
    // at zero; the reference is checked element by element without f64 copies of the buffers.
    let p0: Vec<f32> = (0..HUGE).map(|i| ((i % 1013) as f32 - 506.0) * 1e-3).collect();
    let g: Vec<f32> = (0..HUGE).map(|i| ((i % 997) as f32 - 498.0) * 1e-4).collect();
    let (p, gt) = (f32_tensor(&gpu, &p0), f32_tensor(&gpu, &g));
    // The moments start at zero, written from the host (a fill would bind each whole; AdamW
    // itself goes in chunks, so it also runs under a small binding limit).
    let zeros = vec![0f32; HUGE];
    let (m, v) = (f32_tensor(&gpu, &zeros), f32_tensor(&gpu, &zeros));
    let s = AdamWStep { lr: 1e-2, step: 1, grad_scale: 1.0, max_norm: None };
    let mut rec = gpu.recorder().unwrap();
    let t = AdamWTensors { params: &p, grads: &gt, m: &m, v: &v, decay_len: HUGE / 2, norm: None };
    adamw(&mut rec, &t, &cfg, &s).unwrap();
    rec.submit().unwrap();
    let got = p.read::<f32>().unwrap();
    let (mut err, mut norm) = (0f64, 0f64);
    for i in 0..HUGE {
        let (mut rp, mut rm, mut rv) = ([p0[i] as f64], [0f64], [0f64]);
        adamw::reference::adamw(
            &mut rp,
            &mut rm,
            &mut rv,
            &g[i..i + 1],
            (i < HUGE / 2) as usize,
            None,
            &cfg,
            &s,
        );
        err += (got[i] as f64 - rp[0]).powi(2);
        norm += rp[0] * rp[0];
    }
    eprintln!("adamw on {HUGE} elements: nmse {:.2e}", err / norm);
    assert!(err / norm < 1e-12, "adamw on {HUGE} elements: nmse {:.2e}", err / norm);
}

#[test]
fn global_norm_matches_reference() {
    let gpu = gpu();
    let mut rng = Rng::new(12);
    // 300_000 needs several grid-stride turns of 1024 workgroups.
    for n in [0, 1, 255, 256, 257, 10_007, 300_000] {
        let x: Vec<f32> = rng
            .normal_vec(n)
            .iter()
            .enumerate()
            .map(|(i, v)| if i % 101 == 0 { v * 1e3 } else { *v })
            .collect();
        let t = f32_tensor(&gpu, &x);
        let mut rec = gpu.recorder().unwrap();
        let out = global_norm(&mut rec, &t).unwrap();
        let chunk = 64 * t.view_alignment();
        let scratch = NormScratch::for_chunks(&gpu, n, chunk).unwrap();
        global_norm_chunked(&mut rec, &t, &scratch, chunk).unwrap();
        rec.submit().unwrap();
        let want = norm::reference::global_norm(&x);
        let got = out.read::<f32>().unwrap();
        let chunked = scratch.result().read::<f32>().unwrap();
        eprintln!(
            "norm n={n}: {} want {want}, rel err {:.2e}",
            got[0],
            (got[0] as f64 - want).abs() / want.max(1e-300)
        );
        assert_nmse(&format!("norm of {n}"), &got, &[want, want * want], 1e-12);
        assert_nmse(&format!("norm of {n} in chunks"), &chunked, &[want, want * want], 1e-12);
        assert_eq!(check_finite(&out, "x").unwrap(), got[0]);
    }
}

#[test]
fn nan_and_inf_gradients_are_caught_and_the_step_skipped() {
    let gpu = gpu();
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let n = 5000;
        let mut g = Rng::new(13).normal_vec(n);
        g[4321] = bad;
        let p0 = Rng::new(14).normal_vec(n);
        let (p, gt) = (f32_tensor(&gpu, &p0), f32_tensor(&gpu, &g));
        let (m, v) = (f32_tensor(&gpu, &vec![0.0; n]), f32_tensor(&gpu, &vec![0.0; n]));
        let mut rec = gpu.recorder().unwrap();
        let nt = global_norm(&mut rec, &gt).unwrap();
        let s = AdamWStep { lr: 0.1, step: 1, grad_scale: 1.0, max_norm: Some(1.0) };
        let t = AdamWTensors { params: &p, grads: &gt, m: &m, v: &v, decay_len: n, norm: Some(&nt) };
        adamw(&mut rec, &t, &AdamWConfig::default(), &s).unwrap();
        rec.submit().unwrap();
        let err = check_finite(&nt, "gradients").unwrap_err().to_string();
        assert!(err.contains("NaN or Inf"), "{err}");
        assert_eq!(p.read::<f32>().unwrap(), p0, "parameters changed by a step with {bad} gradients");
        assert!(m.read::<f32>().unwrap().iter().all(|&x| x == 0.0));
    }
}

#[test]
fn adamw_rejects_bad_arguments() {
    let gpu = gpu();
    let a = f32_tensor(&gpu, &[0.0; 8]);
    let b = f32_tensor(&gpu, &[0.0; 7]);
    let mut rec = gpu.recorder().unwrap();
    let ok = AdamWStep { lr: 1e-3, step: 1, grad_scale: 1.0, max_norm: None };
    let t = |g| AdamWTensors { params: &a, grads: g, m: &a, v: &a, decay_len: 0, norm: None };
    let cfg = AdamWConfig::default();
    assert!(adamw(&mut rec, &t(&b), &cfg, &ok).unwrap_err().to_string().contains("grads"));
    assert!(adamw(&mut rec, &t(&a), &cfg, &AdamWStep { step: 0, ..ok })
        .unwrap_err()
        .to_string()
        .contains("from 1"));
    assert!(adamw(&mut rec, &t(&a), &cfg, &AdamWStep { max_norm: Some(1.0), ..ok }).is_err());
    assert!(adamw(&mut rec, &t(&a), &AdamWConfig { beta2: 1.0, ..cfg }, &ok).is_err());
    let long = AdamWTensors { decay_len: 9, ..t(&a) };
    assert!(adamw(&mut rec, &long, &cfg, &ok).is_err());
}

#[test]
fn noam_schedule_values() {
    let s = Noam::new(1e-4, 4000);
    assert_eq!(s.lr(0), 0.0);
    for (step, want) in
        [(1, 2.5e-8), (400, 1e-5), (4000, 1e-4), (16_000, 5e-5), (1_000_000, 6.324_555_320_336_759e-6)]
    {
        assert!(
            (s.lr(step) - want).abs() < 1e-12 * want.max(1e-4),
            "lr({step}) = {} want {want}",
            s.lr(step)
        );
    }
    assert_eq!(noam(4.9e-4, 4000, 4000), 4.9e-4);
}

/// A store of a few awkwardly sized tensors, decayed and not, in mixed order.
fn small_store(gpu: &Gpu, seed: u64, w1_shape: &[usize], extra: bool) -> ParamStore {
    let mut b = ParamStore::builder();
    b.add("enc.norm.gain", &[7], Init::Ones).unwrap();
    b.add("enc.w1", w1_shape, Init::Xavier).unwrap();
    b.add("enc.b1", &[13], Init::Zeros).unwrap();
    b.add("enc.w2", &[13, 5], Init::Kaiming { fan_in: 13 }).unwrap();
    b.add("embed", &[3, 1, 4], Init::Normal { std: 0.02 }).unwrap();
    b.add_with_decay("scale", &[1], Init::Uniform { lo: 0.5, hi: 1.5 }, true).unwrap();
    if extra {
        b.add("head.w", &[4, 4], Init::Xavier).unwrap();
    }
    b.build(gpu, seed).unwrap()
}

/// Fills every gradient with seeded values through the store's views.
fn random_grads(store: &ParamStore, rng: &mut Rng) {
    for (_, p, g) in store.iter() {
        assert_eq!(p.shape(), g.shape());
        g.write(&rng.normal_vec(g.numel())).unwrap();
    }
}

#[test]
fn parameter_store_layout_step_and_norm() {
    let gpu = gpu();
    let mut store = small_store(&gpu, 1, &[13, 7], false);
    let align = store.flat_params().view_alignment();
    let names: Vec<&str> = store.iter().map(|(n, _, _)| n).collect();
    assert_eq!(names, ["enc.norm.gain", "enc.w1", "enc.b1", "enc.w2", "embed", "scale"]);
    assert_eq!(store.num_parameters(), 7 + 91 + 13 + 65 + 12 + 1);
    for info in store.infos() {
        assert_eq!(info.offset % align, 0, "{} at {}", info.name, info.offset);
        let inside_decay = info.offset + info.numel <= store.decay_len();
        assert_eq!(info.decay, inside_decay, "{} decay flag vs layout", info.name);
    }
    assert_eq!(store.param("enc.norm.gain").unwrap().read::<f32>().unwrap(), vec![1.0; 7]);
    assert!(store.param("nope").unwrap_err().to_string().contains("nope"));
    // Same seed, same values; another seed, others.
    let again = small_store(&gpu, 1, &[13, 7], false);
    let other = small_store(&gpu, 2, &[13, 7], false);
    let w = store.param("enc.w1").unwrap().read::<f32>().unwrap();
    assert_eq!(w, again.param("enc.w1").unwrap().read::<f32>().unwrap());
    assert_ne!(w, other.param("enc.w1").unwrap().read::<f32>().unwrap());

    let cfg = AdamWConfig { weight_decay: 0.05, ..AdamWConfig::default() };
    let mut rng = Rng::new(3);
    let p0: Vec<f32> = store.flat_params().read().unwrap();
    let (mut rp, mut rm, mut rv) = (f64s(&p0), vec![0f64; p0.len()], vec![0f64; p0.len()]);
    for step in 1..=4u64 {
        let mut rec = gpu.recorder().unwrap();
        store.zero_grads(&mut rec).unwrap();
        rec.submit().unwrap();
        assert!(store.flat_grads().read::<f32>().unwrap().iter().all(|&x| x == 0.0));
        random_grads(&store, &mut rng);
        let g: Vec<f32> = store.flat_grads().read().unwrap();
        let mut rec = gpu.recorder().unwrap();
        store.adamw_step(&mut rec, &cfg, 1e-2, Some(2.0)).unwrap();
        rec.submit().unwrap();
        let norm = store.grad_norm().unwrap();
        let want = norm::reference::global_norm(&g);
        assert!((norm as f64 - want).abs() < 1e-6 * want, "norm {norm} want {want}");
        let s = AdamWStep { lr: 1e-2, step, grad_scale: 1.0, max_norm: Some(2.0) };
        adamw::reference::adamw(&mut rp, &mut rm, &mut rv, &g, store.decay_len(), Some(want), &cfg, &s);
        assert_eq!(store.step(), step);
    }
    assert_nmse("store params after 4 steps", &store.flat_params().read::<f32>().unwrap(), &rp, 1e-12);
    assert_nmse("store m after 4 steps", &store.moments().0.read::<f32>().unwrap(), &rm, 1e-12);

    // A NaN gradient: the step is refused and undone on the counter.
    let before: Vec<f32> = store.flat_params().read().unwrap();
    store.grad("enc.b1").unwrap().write(&[f32::NAN; 13]).unwrap();
    let mut rec = gpu.recorder().unwrap();
    store.adamw_step(&mut rec, &cfg, 1e-2, Some(2.0)).unwrap();
    rec.submit().unwrap();
    assert!(store.grad_norm().unwrap_err().to_string().contains("NaN"));
    assert_eq!(store.step(), 4);
    assert_eq!(store.flat_params().read::<f32>().unwrap(), before);
}

fn temp_dir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("velox-train-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A store that has taken three steps, so its moments are not zero.
fn trained_store(gpu: &Gpu, seed: u64) -> ParamStore {
    let mut store = small_store(gpu, seed, &[13, 7], false);
    let mut rng = Rng::new(seed + 100);
    for _ in 0..3 {
        random_grads(&store, &mut rng);
        let mut rec = gpu.recorder().unwrap();
        store.adamw_step(&mut rec, &AdamWConfig::default(), 1e-2, Some(1.0)).unwrap();
        rec.submit().unwrap();
        store.grad_norm().unwrap();
    }
    store
}

fn flat_state(store: &ParamStore) -> [Vec<u32>; 3] {
    let bits = |t: &Tensor| t.read::<f32>().unwrap().iter().map(|x| x.to_bits()).collect();
    let (m, v) = store.moments();
    [bits(store.flat_params()), bits(m), bits(v)]
}

#[test]
fn checkpoint_round_trip_is_bit_exact() {
    let gpu = gpu();
    let dir = temp_dir("roundtrip");
    let path = dir.join("ckpt.safetensors");
    let a = trained_store(&gpu, 5);
    let config = r#"{"config": "autoencoder-tiny", "lr": 4.9e-4}"#;
    checkpoint::save(&path, &a, config).unwrap();
    assert!(!temp_path(&path).exists(), "the temporary file is left behind");
    let mut b = small_store(&gpu, 6, &[13, 7], false);
    assert_ne!(flat_state(&a)[0], flat_state(&b)[0]);
    let info = checkpoint::load(&path, &mut b).unwrap();
    assert_eq!(info.step, 3);
    assert_eq!(info.config, config);
    assert_eq!(b.step(), 3);
    assert_eq!(flat_state(&a), flat_state(&b));
    // The same state gives the same bytes, whatever order safetensors' metadata map has in each
    // save (four keys: 24 orders, so eight saves would almost surely show an unsorted one).
    let first = std::fs::read(&path).unwrap();
    for _ in 0..8 {
        checkpoint::save(&path, &a, config).unwrap();
        assert!(std::fs::read(&path).unwrap() == first, "a save of the same state wrote other bytes");
    }
    assert!(checkpoint::save(&path, &a, "not json").unwrap_err().to_string().contains("JSON"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn verify_finite_passes_a_good_checkpoint_and_names_the_tensor_with_a_nan() {
    let gpu = gpu();
    let dir = temp_dir("finite");
    let path = dir.join("ckpt.safetensors");
    let store = trained_store(&gpu, 12);
    checkpoint::save(&path, &store, "{}").unwrap();
    assert_eq!(checkpoint::verify_finite(&path).unwrap().step, 3);
    // read_tensors gives the values as saved.
    let (info, tensors) = checkpoint::read_tensors(&path).unwrap();
    assert_eq!(info.step, 3);
    assert_eq!(tensors.len(), 3 * store.len());
    let w2 = store.infos().iter().find(|p| p.name == "enc.w2").unwrap();
    let host = store.flat_params().read::<f32>().unwrap();
    assert_eq!(tensors["param/enc.w2"], host[w2.offset..w2.offset + w2.numel]);

    // One NaN and one Inf in enc.w2.
    let mut bad = host.clone();
    bad[w2.offset + 3] = f32::NAN;
    bad[w2.offset + 10] = f32::INFINITY;
    store.flat_params().write(&bad).unwrap();
    checkpoint::save(&path, &store, "{}").unwrap();
    let e = file_error(checkpoint::verify_finite(&path), &path, FileOp::Content);
    assert!(e.contains("\"param/enc.w2\" holds 2 NaN or Inf"), "{e}");
    let missing = dir.join("missing.safetensors");
    file_error(checkpoint::verify_finite(&missing), &missing, FileOp::Read);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_checkpoints_give_clear_errors_and_change_nothing() {
    let gpu = gpu();
    let dir = temp_dir("bad");
    let path = dir.join("ckpt.safetensors");
    checkpoint::save(&path, &trained_store(&gpu, 7), "{}").unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let mut store = small_store(&gpu, 8, &[13, 7], false);
    let before = flat_state(&store);
    let load_err = |file: &std::path::Path, store: &mut ParamStore, op: FileOp| {
        file_error(checkpoint::load(file, store), file, op)
    };

    let truncated = dir.join("truncated.safetensors");
    std::fs::write(&truncated, &bytes[..bytes.len() - 100]).unwrap();
    load_err(&truncated, &mut store, FileOp::Content);

    let garbage = dir.join("garbage.safetensors");
    std::fs::write(&garbage, b"\xff\xff\xff\xff not a checkpoint at all").unwrap();
    load_err(&garbage, &mut store, FileOp::Content);

    load_err(&dir.join("missing.safetensors"), &mut store, FileOp::Read);

    // Each mismatch names the tensor.
    let mut wrong_shape = small_store(&gpu, 8, &[7, 13], false);
    let e = load_err(&path, &mut wrong_shape, FileOp::Content);
    assert!(e.contains("\"param/enc.w1\""), "{e}");

    let mut more = small_store(&gpu, 8, &[13, 7], true);
    let e = load_err(&path, &mut more, FileOp::Content);
    assert!(e.contains("\"param/head.w\""), "{e}");
    checkpoint::save(&path, &more, "{}").unwrap();
    let e = load_err(&path, &mut store, FileOp::Content);
    assert!(e.contains("head.w"), "{e}");

    assert_eq!(flat_state(&store), before, "a failed load changed the store");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn load_params_takes_the_parameters_alone_and_names_what_differs() {
    // What `velox train --init` does: another run's parameters, this store's moments and step.
    let gpu = gpu();
    let dir = temp_dir("params");
    let path = dir.join("ckpt.safetensors");
    let trained = trained_store(&gpu, 9);
    checkpoint::save(&path, &trained, "{}").unwrap();
    let mut fresh = small_store(&gpu, 10, &[13, 7], false);
    let [_, m0, v0] = flat_state(&fresh);
    assert_eq!(checkpoint::load_params(&path, &mut fresh).unwrap().step, 3);
    let [p, m, v] = flat_state(&fresh);
    assert_eq!(p, flat_state(&trained)[0], "the parameters are the checkpoint's");
    assert_eq!((m, v, fresh.step()), (m0, v0, 0), "the moments and the step stay the fresh store's");

    let mut wrong_shape = small_store(&gpu, 10, &[7, 13], false);
    let before = flat_state(&wrong_shape);
    let e = file_error(checkpoint::load_params(&path, &mut wrong_shape), &path, FileOp::Content);
    assert!(e.contains("\"param/enc.w1\""), "{e}");
    let mut more = small_store(&gpu, 10, &[13, 7], true);
    let e = file_error(checkpoint::load_params(&path, &mut more), &path, FileOp::Content);
    assert!(e.contains("\"param/head.w\""), "{e}");
    checkpoint::save(&path, &more, "{}").unwrap();
    let loaded = flat_state(&fresh);
    let e = file_error(checkpoint::load_params(&path, &mut fresh), &path, FileOp::Content);
    assert!(e.contains("\"param/head.w\""), "{e}");
    assert_eq!(flat_state(&fresh), loaded, "a refused load changed the store");
    assert_eq!(flat_state(&wrong_shape), before, "a refused load changed the store");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn checkpoints_with_nan_or_inf_are_refused_naming_the_tensor() {
    let gpu = gpu();
    let dir = temp_dir("nonfinite");
    let mut store = small_store(&gpu, 12, &[13, 7], false);
    let before = flat_state(&store);
    // One NaN weight, as a diverged run would leave it.
    let nan = dir.join("nan.safetensors");
    let poisoned = trained_store(&gpu, 13);
    let mut w = poisoned.param("enc.w1").unwrap().read::<f32>().unwrap();
    w[40] = f32::NAN;
    poisoned.param("enc.w1").unwrap().write(&w).unwrap();
    checkpoint::save(&nan, &poisoned, "{}").unwrap();
    let e = file_error(checkpoint::load(&nan, &mut store), &nan, FileOp::Content);
    assert!(e.contains("\"param/enc.w1\" holds 1 NaN or Inf"), "{e}");
    // Two infinite second moments.
    let inf = dir.join("inf.safetensors");
    let poisoned = trained_store(&gpu, 14);
    let v = poisoned.moments().1;
    let mut host = v.read::<f32>().unwrap();
    let at = poisoned.infos().iter().find(|p| p.name == "embed").unwrap().offset;
    host[at] = f32::INFINITY;
    host[at + 1] = f32::NEG_INFINITY;
    v.write(&host).unwrap();
    checkpoint::save(&inf, &poisoned, "{}").unwrap();
    let e = file_error(checkpoint::load(&inf, &mut store), &inf, FileOp::Content);
    assert!(e.contains("\"adamw_v/embed\" holds 2 NaN or Inf"), "{e}");
    assert_eq!(flat_state(&store), before, "a refused load changed the store");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn interrupted_writes_leave_the_previous_checkpoint_intact() {
    let gpu = gpu();
    let dir = temp_dir("atomic");
    let path = dir.join("ckpt.safetensors");
    let old = trained_store(&gpu, 9);
    let new = trained_store(&gpu, 10);
    checkpoint::save(&path, &old, "{}").unwrap();
    let mut probe = small_store(&gpu, 11, &[13, 7], false);

    // A crash half-way through an earlier save left garbage at the temporary path: the
    // checkpoint still loads as it was, and the next save replaces the garbage.
    std::fs::write(temp_path(&path), b"half a checkp").unwrap();
    checkpoint::load(&path, &mut probe).unwrap();
    assert_eq!(flat_state(&probe), flat_state(&old));

    // The temporary file cannot be written (a folder sits in its place): the save fails with
    // a message and the old checkpoint is untouched.
    std::fs::remove_file(temp_path(&path)).unwrap();
    std::fs::create_dir(temp_path(&path)).unwrap();
    file_error(checkpoint::save(&path, &new, "{}"), &path, FileOp::Write);
    checkpoint::load(&path, &mut probe).unwrap();
    assert_eq!(flat_state(&probe), flat_state(&old));
    std::fs::remove_dir(temp_path(&path)).unwrap();

    // The rename cannot happen (the target is a non-empty folder): no temporary file is left.
    let blocked = dir.join("blocked");
    std::fs::create_dir_all(blocked.join("inside")).unwrap();
    assert!(checkpoint::save(&blocked, &new, "{}").is_err());
    assert!(!temp_path(&blocked).exists());

    std::fs::write(temp_path(&path), b"stale").unwrap();
    checkpoint::save(&path, &new, "{}").unwrap();
    checkpoint::load(&path, &mut probe).unwrap();
    assert_eq!(flat_state(&probe), flat_state(&new));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn adamw_minimises_a_quadratic_on_the_gpu() {
    // loss = sum (x - t)^2, gradient 2 (x - t) from the binary and unary ops, AdamW with the
    // noam schedule and clipping, all recorded in one command buffer per step.
    let gpu = gpu();
    let n = 4099;
    let mut b = ParamStore::builder();
    b.add_with_decay("x", &[n], Init::Normal { std: 1.0 }, false).unwrap();
    let mut store = b.build(&gpu, 21).unwrap();
    let target_host = Rng::new(22).normal_vec(n);
    let target = f32_tensor(&gpu, &target_host);
    let loss = |store: &ParamStore| {
        let x: Vec<f32> = store.param("x").unwrap().read().unwrap();
        x.iter().zip(&target_host).map(|(&a, &t)| (a as f64 - t as f64).powi(2)).sum::<f64>()
    };
    let first = loss(&store);
    let schedule = Noam::new(0.1, 20);
    let cfg = AdamWConfig { weight_decay: 0.0, ..AdamWConfig::default() };
    for _ in 0..400 {
        let mut rec = gpu.recorder().unwrap();
        let (x, g) = (store.param("x").unwrap().clone(), store.grad("x").unwrap().clone());
        binary_into(&mut rec, &x, &target, &g, Binary::Sub).unwrap();
        unary_into(&mut rec, &g, &g, Unary::Affine(2.0, 0.0)).unwrap();
        let lr = schedule.lr(store.step() + 1);
        store.adamw_step(&mut rec, &cfg, lr, Some(1.0)).unwrap();
        rec.submit().unwrap();
        store.grad_norm().unwrap();
    }
    let last = loss(&store);
    eprintln!("quadratic: loss {first:.3e} -> {last:.3e} ({:.1e}x)", first / last);
    assert!(last * 1e4 < first, "loss fell from {first:.3e} only to {last:.3e}");
}

/// Would catch: a weights file that does not read back as the parameters it was written from
/// (a part left out, a tensor in the wrong part, f16 rounding gone wrong), one that a run could
/// resume from (it has no moments), and a split file whose missing part is not named.
#[test]
fn weights_files_hold_the_parameters_alone_in_parts_and_refuse_a_resume() {
    use checkpoint::WeightsDtype;
    let gpu = gpu();
    let dir = temp_dir("weights");
    let ckpt = dir.join("ckpt.safetensors");
    let trained = trained_store(&gpu, 21);
    checkpoint::save(&ckpt, &trained, r#"{"model": "test", "run": {"seed": 1}}"#).unwrap();
    let params = flat_state(&trained)[0].clone();

    // f32 in parts of at most 5 KiB: several parts, which read back as the whole, from any part
    // or from the unsplit name.
    let whole = dir.join("w32.safetensors");
    let parts = checkpoint::save_weights(&ckpt, &whole, WeightsDtype::F32, Some(5 << 10)).unwrap();
    assert!(parts.len() > 1, "{parts:?}");
    assert!(parts.iter().all(|p| std::fs::metadata(p).unwrap().len() <= 5 << 10));
    assert!(!whole.exists());
    for name in [whole.clone(), parts[parts.len() - 1].clone()] {
        let mut fresh = small_store(&gpu, 22, &[13, 7], false);
        let info = checkpoint::load_model(&name, &mut fresh).unwrap();
        assert!(info.weights_only && info.step == 3);
        assert_eq!(flat_state(&fresh)[0], params, "{}", name.display());
        assert_eq!(fresh.step(), 3);
        // The run's settings stay behind: a weights file starts no resumed run.
        assert!(!info.config.contains("\"run\""), "{}", info.config);
    }
    // A full load (what a resumed run does) is refused, naming why.
    let mut fresh = small_store(&gpu, 22, &[13, 7], false);
    let e = file_error(checkpoint::load(&whole, &mut fresh), &whole, FileOp::Content);
    assert!(e.contains("weights only"), "{e}");
    // A missing part is named.
    std::fs::remove_file(&parts[1]).unwrap();
    file_error(checkpoint::load_model(&whole, &mut fresh), &parts[1], FileOp::Read);

    // f16, unsplit: each value is the f16 rounding of the f32 one.
    let w16 = dir.join("w16.safetensors");
    assert_eq!(
        checkpoint::save_weights(&ckpt, &w16, WeightsDtype::F16, None).unwrap(),
        std::slice::from_ref(&w16)
    );
    let mut fresh = small_store(&gpu, 22, &[13, 7], false);
    checkpoint::load_model(&w16, &mut fresh).unwrap();
    let want: Vec<u32> = trained
        .flat_params()
        .read::<f32>()
        .unwrap()
        .iter()
        .map(|&v| half::f16::from_f32(v).to_f32().to_bits())
        .collect();
    assert_eq!(flat_state(&fresh)[0], want);
    // A parameter past f16's range is refused by name, not written as an infinity.
    let mut big = trained.flat_params().read::<f32>().unwrap();
    let w2 = trained.infos().iter().find(|p| p.name == "enc.w2").unwrap().offset;
    big[w2] = 1e6;
    trained.flat_params().write(&big).unwrap();
    checkpoint::save(&ckpt, &trained, "{}").unwrap();
    let e = checkpoint::save_weights(&ckpt, &w16, WeightsDtype::F16, None).unwrap_err().to_string();
    assert!(e.contains("enc.w2") && e.contains("f16"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
