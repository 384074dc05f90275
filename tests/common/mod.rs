//! Shared by the root test binaries: the engine tests' device and reference checks, and the
//! helpers of the model, data and training tests.
#![allow(dead_code, unused_imports)]

#[path = "../../engine/tests/common/mod.rs"]
mod device;
pub use device::*;

/// Standard base64 with padding, for data: URIs.
pub fn base64(bytes: &[u8]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::new();
    for c in bytes.chunks(3) {
        let n = (c[0] as u32) << 16 | (*c.get(1).unwrap_or(&0) as u32) << 8 | *c.get(2).unwrap_or(&0) as u32;
        for k in 0..4 {
            if k <= c.len() {
                s.push(T[(n >> (18 - 6 * k)) as usize & 63] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

/// A GLB file of a JSON document and a binary chunk, each padded to 4 bytes.
pub fn glb(json: &str, bin: &[u8]) -> Vec<u8> {
    let mut j = json.as_bytes().to_vec();
    while !j.len().is_multiple_of(4) {
        j.push(b' ');
    }
    let mut b = bin.to_vec();
    while !b.len().is_multiple_of(4) {
        b.push(0);
    }
    let total = 12 + 8 + j.len() + 8 + b.len();
    let mut out = Vec::new();
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((j.len() as u32).to_le_bytes());
    out.extend(0x4E4F_534Au32.to_le_bytes());
    out.extend(j);
    out.extend((b.len() as u32).to_le_bytes());
    out.extend(0x004E_4942u32.to_le_bytes());
    out.extend(b);
    out
}

/// The total loss of each of `steps` steps of the library trainer, from the model as given,
/// in `precision`: every step a global batch of `samples` (micro-batches of the model's own
/// size, accumulated).
pub fn trainer_losses<M: velox::models::train::Trainable>(
    model: &mut M,
    samples: &[&M::Sample],
    steps: u64,
    precision: velox::engine::Precision,
) -> Vec<f64> {
    use velox::models::run::{RunRequest, RunSettings};
    use velox::models::train::collective::SingleProcess;
    use velox::models::train::trainer::Trainer;
    let micro = model.optimisation().batch as u64;
    assert_eq!(
        samples.len() as u64 % micro,
        0,
        "{} samples are not whole micro-batches of {micro}",
        samples.len()
    );
    let request = RunRequest {
        steps: Some(steps),
        precision: Some(precision),
        accumulate: Some(samples.len() as u64 / micro),
        ..Default::default()
    };
    let names = (0..samples.len()).map(|i| format!("sample {i}")).collect();
    let settings = RunSettings::new(&request, names, micro, 1).unwrap();
    let mut trainer = Trainer::new(model, &SingleProcess, settings).unwrap();
    let reports = trainer.repeat_steps(samples, 1..steps + 1).unwrap();
    reports.iter().map(|r| r.losses.total()).collect()
}

/// Trains two models from `make` for `steps` f16 steps of one micro-batch on `samples`, one
/// with each step recorded while the last runs and one without, and fails unless their
/// parameters and reports are the same to the bit and every step after the first was
/// recorded ahead and run as recorded.
pub fn recorded_ahead_is_the_same<M: velox::models::train::Trainable>(
    make: impl Fn() -> M,
    samples: &[&M::Sample],
    steps: u64,
) {
    use velox::models::run::{RunRequest, RunSettings};
    use velox::models::train::collective::SingleProcess;
    use velox::models::train::trainer::Trainer;
    let run = |overlap: bool| {
        let mut model = make();
        let request = RunRequest {
            steps: Some(steps),
            precision: Some(velox::engine::Precision::F16),
            ..Default::default()
        };
        let names = vec!["sample".to_string()];
        let micro = model.optimisation().batch as u64;
        assert_eq!(samples.len() as u64, micro, "one micro-batch a step");
        let settings = RunSettings::new(&request, names, micro, 1).unwrap();
        let mut trainer = Trainer::new(&mut model, &SingleProcess, settings).unwrap();
        trainer.set_overlap(overlap);
        let reports = trainer.repeat_steps(samples, 1..steps + 1).unwrap();
        let ahead = trainer.recorded_ahead();
        let key: Vec<_> =
            reports.iter().map(|r| (r.losses.total().to_bits(), r.grad_norm.to_bits())).collect();
        (model.store().flat_params().read::<f32>().unwrap(), key, ahead)
    };
    let (want, want_reports, _) = run(false);
    let (got, reports, ahead) = run(true);
    assert_eq!(ahead, (steps - 1, steps - 1), "steps recorded ahead, and run as recorded");
    assert!(got == want, "steps recorded ahead changed the parameters");
    assert_eq!(reports, want_reports);
}

/// The largest and the mean relative difference of `half`'s losses from `full`'s, step by step.
pub fn relative_gaps(full: &[f64], half: &[f64]) -> (f64, f64) {
    assert_eq!(full.len(), half.len());
    let rel: Vec<f64> = full.iter().zip(half).map(|(a, b)| (a - b).abs() / a.abs()).collect();
    (rel.iter().cloned().fold(0.0, f64::max), rel.iter().sum::<f64>() / rel.len() as f64)
}

/// Mean of a run of losses.
pub fn mean_of(losses: &[f64]) -> f64 {
    losses.iter().sum::<f64>() / losses.len() as f64
}

/// Replaces every parameter of `store` with normal values of standard deviation
/// `gain / sqrt(fan_in)` (matrices) or `0.2` (vectors), so that every path of a network (the
/// zero-initialised adaLN maps and output layers included, and a head whose small start would
/// shrink every gradient upstream of it) carries a gradient of its own size.
pub fn randomize_params(store: &velox::models::params::ParamStore, seed: u64, gain: f32) {
    let mut rng = Rng::new(seed);
    for info in store.infos() {
        let s = &info.shape;
        let std = if s.len() >= 2 { gain / (s[s.len() - 2] as f32).sqrt() } else { 0.2 };
        let v: Vec<f32> = rng.normal_vec(info.numel).iter().map(|x| x * std).collect();
        store.write_param(&info.name, &v).unwrap();
    }
}

/// A set of parameter tensors a finite-difference check moves together: a name and the flat
/// ranges (in the store's parameter vector) of its tensors.
pub struct ParamGroup {
    pub name: String,
    pub ranges: Vec<std::ops::Range<usize>>,
}

impl ParamGroup {
    /// Every tensor whose name starts with `prefix` ("" for all of them).
    pub fn under(store: &velox::models::params::ParamStore, prefix: &str) -> ParamGroup {
        let ranges: Vec<_> = store
            .infos()
            .iter()
            .filter(|i| i.name.starts_with(prefix))
            .map(|i| i.offset..i.offset + i.numel)
            .collect();
        assert!(!ranges.is_empty(), "no parameter under {prefix:?}");
        let name = if prefix.is_empty() { "every parameter".to_string() } else { format!("{prefix}*") };
        ParamGroup { name, ranges }
    }

    /// Each tensor alone.
    pub fn each(store: &velox::models::params::ParamStore) -> Vec<ParamGroup> {
        store
            .infos()
            .iter()
            .map(|i| ParamGroup {
                name: i.name.clone(),
                ranges: std::iter::once(i.offset..i.offset + i.numel).collect(),
            })
            .collect()
    }
}

/// Checks a gradient against finite differences of its loss: for each group, along `trials`
/// random directions over that group's tensors (zero elsewhere), the derivative `grads . u`
/// against the median of the slopes `(L(theta + (k+1) h u) - L(theta + k h u)) / h` for
/// `k = -steps .. steps - 1`, within `rel * |analytic| + abs`. With `steps` 1 that is the
/// central difference; more steps make it robust to a loss that jumps (a rasteriser's depth
/// order or alpha threshold: a jump spoils one slope, not the median). `loss_at` writes the
/// parameters it is given into the model and returns the loss (it must draw the same samples
/// every time). Returns the worst `|estimate - analytic| / |analytic|`, and prints every
/// figure under `VELOX_TEST_VERBOSE`. The parameters are left at `theta`.
#[allow(clippy::too_many_arguments)]
#[track_caller]
pub fn check_directional(
    what: &str,
    theta: &[f32],
    grads: &[f32],
    groups: &[ParamGroup],
    (trials, steps): (usize, i32),
    h: f32,
    (rel, abs): (f64, f64),
    rng: &mut Rng,
    loss_at: &mut dyn FnMut(&[f32]) -> f64,
) -> f64 {
    assert_eq!(theta.len(), grads.len());
    assert!(grads.iter().all(|g| g.is_finite()), "{what}: a non-finite gradient");
    assert!(steps >= 1);
    let mut worst = 0f64;
    for group in groups {
        for trial in 0..trials {
            let mut u = vec![0f32; theta.len()];
            for r in &group.ranges {
                u[r.clone()].copy_from_slice(&rng.normal_vec(r.len()));
            }
            let analytic: f64 = grads.iter().zip(&u).map(|(&g, &v)| g as f64 * v as f64).sum();
            let losses: Vec<f64> = (-steps..=steps)
                .map(|k| {
                    let s = k as f32 * h;
                    loss_at(&theta.iter().zip(&u).map(|(&p, &v)| p + s * v).collect::<Vec<_>>())
                })
                .collect();
            let mut slopes: Vec<f64> = losses.windows(2).map(|w| (w[1] - w[0]) / h as f64).collect();
            slopes.sort_by(f64::total_cmp);
            let estimate = (slopes[slopes.len() / 2 - 1] + slopes[slopes.len() / 2]) / 2.0;
            let err = (estimate - analytic).abs();
            let r = err / analytic.abs().max(1e-30);
            worst = worst.max(r);
            if verbose() {
                eprintln!(
                    "{what}, {} #{trial}: analytic {analytic:+.6e} finite difference {estimate:+.6e} relative {r:.2e}",
                    group.name
                );
            }
            assert!(
                err <= rel * analytic.abs() + abs,
                "{what}, {} (direction {trial}): analytic {analytic:e} against finite difference {estimate:e} ({r:.2e})",
                group.name
            );
        }
    }
    loss_at(theta);
    worst
}

/// The reason of a file error about `path` of kind `op` (the test fails on any other outcome):
/// tests match the variant, the path and the operation, and the reason where it must name
/// something (a tensor, a point).
pub fn file_error<T: std::fmt::Debug>(
    r: velox::engine::Result<T>,
    path: &std::path::Path,
    op: velox::engine::FileOp,
) -> String {
    match r {
        Err(velox::engine::Error::File { path: p, op: o, reason }) if p == path && o == op => reason,
        other => panic!("expected a {op:?} error of {}, got {other:?}", path.display()),
    }
}
