//! The op-case harness: every op of the engine with an f64 reference, run forward and (where it
//! has one) backward at several shapes, each output held to its row's bound; and every
//! reference backward checked against central finite differences of the reference forward, so
//! that the f64 reference the kernels are held to is itself right. A row of [`CASES`] is the
//! op, its shapes, its NMSE bound (with the reason beside it), a function that runs it on random
//! inputs and returns its outputs beside the reference's, and, for an op with a backward, the
//! function that checks its reference's gradients. `VELOX_TEST_VERBOSE=1` prints every case's
//! NMSE against its bound; a failure lists every case over its bound, not just the first.
//!
//! Adding an op is one row here, its kernel in `shaders/`, and its host side with a `reference`
//! module in `engine/src/ops/`. The op families' own test files keep what a row cannot say: edge
//! cases (empty tensors, more workgroups than one dispatch dimension takes, bindings past the
//! limit), pointwise bounds, f16 paths, determinism and the errors of bad input.

use crate::common;
use common::*;
use velox_engine::ops::adaln;
use velox_engine::ops::adamw::{self, adamw, AdamWConfig, AdamWStep, AdamWTensors};
use velox_engine::ops::assign::{self, assign_nearest};
use velox_engine::ops::attention::{self, attention, attention_backward, Segments};
use velox_engine::ops::binary::{self, binary, Binary};
use velox_engine::ops::cast::{self, cast};
use velox_engine::ops::cloth::{self, ClothMesh, ClothParams, ClothSim};
use velox_engine::ops::columns::{self, columns};
use velox_engine::ops::concat;
use velox_engine::ops::fourier::{self, fourier, fourier_backward, fourier_width};
use velox_engine::ops::fps::{self, fps};
use velox_engine::ops::gather::{self, gather};
use velox_engine::ops::gaussian_head::{self, head_backward, head_forward, HeadRange};
use velox_engine::ops::layernorm::{self, layernorm, layernorm_backward};
use velox_engine::ops::loss::{self, loss, LossKind};
use velox_engine::ops::matmul::{self, matmul};
use velox_engine::ops::norm::{self, global_norm};
use velox_engine::ops::raster::{self, BackwardKernel, Camera, GaussianSet};
use velox_engine::ops::reduce::{self, reduce, Reduce};
use velox_engine::ops::rmsnorm::{self, rmsnorm, rmsnorm_backward};
use velox_engine::ops::scan::{self, exclusive_scan};
use velox_engine::ops::scatter_add::{self, scatter_add};
use velox_engine::ops::softmax::{self, softmax};
use velox_engine::ops::sort::{self, sort_pairs};
use velox_engine::ops::swiglu::{self, swiglu, swiglu_backward};
use velox_engine::ops::unary::{self, unary, unary_backward, Unary};
use velox_engine::ops::voxel_head;
use velox_engine::ops::window::{self, group_by_window, window_ids, WindowGrid};
use velox_engine::{Recorder, Result};

/// One output of a case beside its reference.
struct Output {
    name: String,
    got: Vec<f64>,
    want: Vec<f64>,
}

fn out(name: impl Into<String>, got: &Tensor, want: Vec<f64>) -> Result<Output> {
    Ok(Output { name: name.into(), got: f64s(&got.read::<f32>()?), want })
}

/// An integer output, compared exactly (bound 0).
fn out_u32(name: impl Into<String>, got: &Tensor, want: &[u32]) -> Result<Output> {
    let wide = |v: &[u32]| v.iter().map(|&x| x as f64).collect::<Vec<f64>>();
    Ok(Output { name: name.into(), got: wide(&got.read::<u32>()?), want: wide(want) })
}

type Run = fn(&Gpu, &[usize], &mut Rng) -> Result<Vec<Output>>;

/// A reference gradient beside central finite differences of the reference forward: the
/// analytic values, the numeric ones and the bound on `|fd - g| / (1 + |g|)`.
struct Gradient {
    name: String,
    analytic: Vec<f64>,
    numeric: Vec<f64>,
    tolerance: f64,
}

type GradientCheck = fn(&mut Rng) -> Vec<Gradient>;

/// Central differences of `loss` in every element of every input, at step `eps`.
fn central_differences(inputs: &[Vec<f64>], loss: impl Fn(&[Vec<f64>]) -> f64, eps: f64) -> Vec<Vec<f64>> {
    (0..inputs.len())
        .map(|k| {
            (0..inputs[k].len())
                .map(|i| {
                    let (mut p, mut m) = (inputs.to_vec(), inputs.to_vec());
                    p[k][i] += eps;
                    m[k][i] -= eps;
                    (loss(&p) - loss(&m)) / (2.0 * eps)
                })
                .collect()
        })
        .collect()
}

/// The gradients `analytic[k]` (of input `k`, named `names[k]`) beside central differences of
/// `loss`, with the step and bound that suit a smooth f64 function of inputs near 1 (the
/// central difference's truncation error is about eps^2 times the third derivative, its
/// rounding 1e-16 / eps).
fn against_differences(
    op: &str,
    names: &[&str],
    inputs: &[Vec<f64>],
    analytic: Vec<Vec<f64>>,
    loss: impl Fn(&[Vec<f64>]) -> f64,
) -> Vec<Gradient> {
    differences_with(op, names, inputs, analytic, loss, 1e-6, 1e-8)
}

fn differences_with(
    op: &str,
    names: &[&str],
    inputs: &[Vec<f64>],
    analytic: Vec<Vec<f64>>,
    loss: impl Fn(&[Vec<f64>]) -> f64,
    eps: f64,
    tolerance: f64,
) -> Vec<Gradient> {
    assert_eq!(analytic.len(), names.len(), "{op}: one name per gradient");
    let numeric = central_differences(
        &inputs[..analytic.len()],
        |v| {
            let mut all = inputs.to_vec();
            all[..v.len()].clone_from_slice(v);
            loss(&all)
        },
        eps,
    );
    analytic
        .into_iter()
        .zip(numeric)
        .zip(names)
        .map(|((analytic, numeric), name)| Gradient {
            name: format!("{op} {name}"),
            analytic,
            numeric,
            tolerance,
        })
        .collect()
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn normals(rng: &mut Rng, n: usize) -> Vec<f64> {
    (0..n).map(|_| rng.normal()).collect()
}

/// An op at its shapes, held to one NMSE bound against its reference (0: exact).
struct Case {
    op: &'static str,
    shapes: &'static [&'static [usize]],
    bound: f64,
    run: Run,
    /// For an op with a backward: its reference's gradients against finite differences.
    gradient: Option<GradientCheck>,
}

/// Rows by width: one row and one column, sizes off every power of two, and one past a
/// workgroup of 256.
const ROWS: &[&[usize]] = &[&[1, 1], &[3, 7], &[17, 64], &[65, 255], &[257, 130]];
/// Rows of softmax: those above, and rows of a multiple of 4 of every length class (one vec4,
/// a few, past a workgroup of 256 values on GPUs, past 1024), which CPU devices run as vec4s in
/// two passes (`shaders/softmax_cpu.wgsl`) and GPUs with a power of two of invocations a row.
const SOFTMAX_ROWS: &[&[usize]] = &[
    &[1, 1],
    &[3, 7],
    &[17, 64],
    &[65, 255],
    &[257, 130],
    &[5, 4],
    &[1500, 8],
    &[9, 36],
    &[11, 100],
    &[33, 132],
    &[7, 260],
    &[5, 516],
    &[6, 1024],
    &[3, 1028],
];
/// Rows of the normalisations: a width of one normalises every row to +-w, and its gradient is
/// a difference of two nearly equal terms (relative error 1e-4 in f32 whatever the kernel), so
/// the narrowest rows here have five values.
const NORM_ROWS: &[&[usize]] = &[&[1, 5], &[3, 7], &[17, 64], &[65, 255], &[257, 130]];
/// Cloth sheets by side: 4 particles (two triangles on one hinge), 49, and 289 (past a
/// workgroup of 256).
const SHEETS: &[&[usize]] = &[&[2], &[7], &[17]];
/// Flat lengths.
const FLAT: &[&[usize]] = &[&[1], &[255], &[257], &[10_007]];
/// Point counts of the query-sampling ops: below, at and past a workgroup of 256 and 1024.
const POINTS: &[&[usize]] = &[&[1], &[300], &[1500], &[5000]];

// The f32 ops round once per value or sum in f32 over at most a few thousand terms: their NMSE
// sits near 1e-14 to 1e-12 on lavapipe; the bounds leave two orders of magnitude for devices
// that round their builtins (exp, division, rsqrt) as loosely as Vulkan allows.
const CASES: &[Case] = &[
    Case { op: "unary", shapes: FLAT, bound: 1e-9, run: unary_case, gradient: Some(unary_gradients) },
    Case { op: "binary", shapes: ROWS, bound: 1e-12, run: binary_case, gradient: None },
    Case { op: "reduce", shapes: ROWS, bound: 1e-10, run: reduce_case, gradient: None },
    Case { op: "softmax", shapes: SOFTMAX_ROWS, bound: 1e-10, run: softmax_case, gradient: None },
    Case { op: "gather", shapes: ROWS, bound: 0.0, run: gather_case, gradient: None },
    Case { op: "scatter_add", shapes: ROWS, bound: 1e-12, run: scatter_case, gradient: None },
    Case { op: "columns", shapes: ROWS, bound: 1e-14, run: columns_case, gradient: None },
    // f32 -> f16 rounds to nearest even, exactly as the reference.
    Case { op: "cast", shapes: FLAT, bound: 0.0, run: cast_case, gradient: None },
    Case { op: "concat", shapes: FLAT, bound: 0.0, run: concat_case, gradient: None },
    Case { op: "scan", shapes: FLAT, bound: 0.0, run: scan_case, gradient: None },
    // [n, key bits]
    Case {
        op: "sort",
        shapes: &[&[1, 32], &[300, 7], &[5000, 16], &[70_000, 32]],
        bound: 0.0,
        run: sort_case,
        gradient: None,
    },
    // [m, k, n]
    Case {
        op: "matmul",
        // (Multiples of 4 take the CPU kernel on CPU devices.)
        shapes: &[&[1, 1, 1], &[3, 7, 5], &[65, 130, 33], &[128, 64, 257], &[36, 68, 132]],
        bound: 1e-10,
        run: matmul_case,
        gradient: None,
    },
    Case { op: "global_norm", shapes: FLAT, bound: 1e-12, run: norm_case, gradient: None },
    Case {
        op: "rmsnorm",
        shapes: NORM_ROWS,
        bound: 1e-10,
        run: rmsnorm_case,
        gradient: Some(rmsnorm_gradients),
    },
    Case {
        op: "layernorm",
        shapes: NORM_ROWS,
        bound: 1e-10,
        run: layernorm_case,
        gradient: Some(layernorm_gradients),
    },
    Case { op: "swiglu", shapes: ROWS, bound: 1e-10, run: swiglu_case, gradient: Some(swiglu_gradients) },
    // [b, t, d]
    Case {
        op: "adaln",
        shapes: &[&[1, 1, 1], &[2, 3, 17], &[3, 100, 64]],
        bound: 1e-12,
        run: adaln_case,
        gradient: Some(adaln_gradients),
    },
    // sin(f x) with f x rounded to f32 first: at the top octave (f = 512 pi, |x| <= 1) the
    // argument is off by up to 1608 * 6e-8 = 1e-4 radians, an NMSE near 1e-9 (measured 7e-10
    // forward, 5e-9 backward, whose rows carry a factor f). [rows, channels, frequencies]
    Case {
        op: "fourier",
        shapes: &[&[1, 1, 1], &[17, 3, 6], &[257, 4, 10]],
        bound: 1e-8,
        run: fourier_case,
        gradient: Some(fourier_gradients),
    },
    Case { op: "loss", shapes: FLAT, bound: 1e-10, run: loss_case, gradient: Some(loss_gradients) },
    // [queries, keys, heads, head width]
    Case {
        op: "attention",
        shapes: &[&[1, 1, 1, 16], &[17, 33, 2, 32], &[70, 65, 3, 64]],
        bound: 1e-10,
        run: attention_case,
        gradient: Some(attention_gradients),
    },
    // [voxels, Gaussians per voxel]
    Case {
        op: "gaussian_head",
        shapes: &[&[1, 1], &[7, 64], &[300, 8]],
        bound: 1e-12,
        run: gaussian_head_case,
        gradient: Some(gaussian_head_gradients),
    },
    // [cells, voxels per cell, hidden width]; GELU's erfc is good to 1.5e-7 absolute.
    Case {
        op: "voxel_head",
        shapes: &[&[1, 1, 1], &[3, 8, 5], &[7, 27, 16]],
        bound: 1e-12,
        run: voxel_head_case,
        gradient: Some(voxel_head_gradients),
    },
    // One step of f32 arithmetic per element against the f64 step.
    Case { op: "adamw", shapes: FLAT, bound: 1e-12, run: adamw_case, gradient: None },
    // Integer results of exact f32 comparisons on grid points (ties broken as the reference).
    // [points, queries]
    Case {
        op: "assign",
        shapes: &[&[1, 1], &[513, 256], &[2000, 257]],
        bound: 0.0,
        run: assign_case,
        gradient: None,
    },
    Case { op: "fps", shapes: POINTS, bound: 0.0, run: fps_case, gradient: None },
    // The positions after 4 frames of 4 substeps: measured 4.2e-10 at side 7, 1e-12 at the
    // others (a contact decided at f32 rounding of its threshold moves a particle by a slide's
    // rounding). Velocities, a position difference over 2.5 ms divided by slides of 1e-5 at a
    // contact, are held to 3e-5 in tests/data/cloth.rs.
    Case { op: "cloth", shapes: SHEETS, bound: 1e-8, run: cloth_case, gradient: None },
    Case { op: "window", shapes: POINTS, bound: 0.0, run: window_case, gradient: None },
    // The f32 projection and blend of a few hundred Gaussians: NMSE near 4e-13 forward and 3e-12
    // backward on lavapipe (engine/tests/ops/raster.rs has the stress scenes, the other backward
    // kernels and the closed forms). [Gaussians, width, height]
    Case {
        op: "raster",
        shapes: &[&[1, 16, 16], &[120, 37, 29], &[300, 64, 48]],
        bound: 1e-10,
        run: raster_case,
        gradient: Some(raster_gradients),
    },
];

fn upload(gpu: &Gpu, shape: &[usize], data: &[f32]) -> Result<Tensor> {
    Tensor::from_slice(gpu, shape, data)
}

/// Records `f` and submits it.
fn recorded<T>(gpu: &Gpu, f: impl FnOnce(&mut Recorder) -> Result<T>) -> Result<T> {
    let mut rec = gpu.recorder()?;
    let t = f(&mut rec)?;
    rec.submit()?;
    Ok(t)
}

/// Would catch: a kernel whose output or gradient leaves its reference at any of the awkward
/// shapes, forward or backward.
#[test]
fn every_op_matches_its_reference_at_every_shape() {
    let gpu = gpu();
    let mut rng = Rng::new(2024);
    let (mut rows, mut over) = (Vec::new(), Vec::new());
    for case in CASES {
        for shape in case.shapes {
            let outputs =
                (case.run)(&gpu, shape, &mut rng).unwrap_or_else(|e| panic!("{} at {shape:?}: {e}", case.op));
            for o in outputs {
                assert_eq!(o.got.len(), o.want.len(), "{} {} at {shape:?}: lengths", case.op, o.name);
                let e = nmse(&o.got, &o.want);
                let row = format!(
                    "{:<14} {:<22} {:<18} nmse {e:9.2e}  bound {:7.0e}",
                    case.op,
                    o.name,
                    format!("{shape:?}"),
                    case.bound
                );
                if e.is_nan() || e > case.bound {
                    over.push(row.clone());
                }
                rows.push(row);
            }
        }
    }
    if verbose() || !over.is_empty() {
        eprintln!("{}", rows.join("\n"));
    }
    assert!(over.is_empty(), "cases over their bound:\n{}", over.join("\n"));
    assert!(rows.len() >= 150, "{} cases ran", rows.len());
}

/// Would catch: a reference backward that is not the derivative of its forward (the kernels
/// would then match a wrong gradient), for every op with a backward.
#[test]
fn every_reference_gradient_matches_finite_differences() {
    let mut rng = Rng::new(2025);
    let (mut rows, mut over) = (Vec::new(), Vec::new());
    for case in CASES {
        let Some(check) = case.gradient else { continue };
        for g in check(&mut rng) {
            assert_eq!(g.analytic.len(), g.numeric.len(), "{}: lengths", g.name);
            assert!(!g.analytic.is_empty(), "{}: no values", g.name);
            let worst = g
                .analytic
                .iter()
                .zip(&g.numeric)
                .map(|(a, n)| (n - a).abs() / (1.0 + a.abs()))
                .fold(0.0, f64::max);
            let row = format!("{:<40} worst {worst:9.2e}  bound {:7.0e}", g.name, g.tolerance);
            if worst.is_nan() || worst > g.tolerance {
                over.push(row.clone());
            }
            rows.push(row);
        }
    }
    if verbose() || !over.is_empty() {
        eprintln!("{}", rows.join("\n"));
    }
    assert!(over.is_empty(), "gradients off their finite differences:\n{}", over.join("\n"));
}

/// Would catch: an op added to a shader's switch without its host-side variant (or the other way
/// round), or two variants sharing a code: every op code the build exports from
/// `shaders/unary.wgsl`, `binary.wgsl`, `reduce.wgsl` and `loss.wgsl` is one variant's, and the
/// harness runs every variant.
#[test]
fn every_op_code_of_a_shader_has_its_variant() {
    use velox_engine::kernels::{BINARY_OPS, LOSS_OPS, REDUCE_OPS, UNARY_OPS};
    let check = |family: &str, table: &[(&str, u32)], codes: Vec<u32>| {
        let mut sorted = codes.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), codes.len(), "{family}: two variants share an op code: {codes:?}");
        let exported: Vec<u32> = table.iter().map(|&(_, c)| c).collect();
        assert_eq!(sorted, exported, "{family}: the variants' codes {sorted:?}, the shader's {table:?}");
    };
    check("unary", UNARY_OPS, Unary::ALL.iter().map(|f| f.code().0).collect());
    check("binary", BINARY_OPS, Binary::ALL.iter().map(|b| b.code()).collect());
    check("reduce", REDUCE_OPS, Reduce::ALL.iter().map(|r| r.code()).collect());
    check("loss", LOSS_OPS, LOSS_KINDS.iter().map(|k| k.code().0).collect());
}

/// Would catch: an op with a backward whose reference gradient goes unchecked.
#[test]
fn every_case_with_a_backward_checks_its_gradient() {
    let gpu = gpu();
    let mut rng = Rng::new(7);
    for case in CASES {
        let names: Vec<String> =
            (case.run)(&gpu, case.shapes[0], &mut rng).unwrap().into_iter().map(|o| o.name).collect();
        let backward = names.iter().any(|n| n.starts_with('d') || n.contains("grad"));
        assert_eq!(
            backward,
            case.gradient.is_some(),
            "{}: outputs {names:?}, a gradient check {}",
            case.op,
            if case.gradient.is_some() { "without a backward" } else { "missing" }
        );
    }
}

/// Every loss kind, with its parameter.
const LOSS_KINDS: &[LossKind] = &[
    LossKind::Mse,
    LossKind::L1,
    LossKind::Huber { delta: 0.5 },
    LossKind::BceWithLogits,
    LossKind::Focal { gamma: 2.0 },
];

/// Inputs where every unary map is finite and well conditioned (and, for the derivatives'
/// finite differences, away from the kinks of abs and relu).
fn unary_input(f: Unary, n: usize, rng: &mut Rng) -> Vec<f32> {
    match f {
        Unary::Log | Unary::Sqrt | Unary::Rsqrt => rng.uniform_vec(n, 1e-3, 100.0),
        Unary::Recip => rng.uniform_vec(n, 0.1, 10.0),
        Unary::Exp => rng.uniform_vec(n, -20.0, 20.0),
        _ => rng.normal_vec(n).iter().map(|v| 4.0 * v).collect(),
    }
}

fn unary_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let mut outs = Vec::new();
    for &f in Unary::ALL {
        let (x, dy) = (unary_input(f, s[0], rng), rng.normal_vec(s[0]));
        let (y, dx) = recorded(gpu, |rec| {
            let xt = upload(gpu, s, &x)?;
            Ok((unary(rec, &xt, f)?, unary_backward(rec, &xt, &upload(gpu, s, &dy)?, f)?))
        })?;
        outs.push(out(format!("{f:?}"), &y, unary::reference::unary(&x, f))?);
        outs.push(out(format!("d {f:?}"), &dx, unary::reference::unary_backward(&f64s(&x), &f64s(&dy), f))?);
    }
    Ok(outs)
}

fn unary_gradients(rng: &mut Rng) -> Vec<Gradient> {
    let mut checks = Vec::new();
    for &f in Unary::ALL {
        // Seven points of the map's domain, each at least 1e-3 from a kink.
        // (exp over [-4, 4] only: beside e^20, the rounding of the sum would swamp e^-20's slope.)
        let x: Vec<f64> = match f {
            Unary::Exp => normals(rng, 7).iter().map(|v| v.clamp(-4.0, 4.0)).collect(),
            _ => {
                unary_input(f, 7, rng).iter().map(|&v| if v.abs() < 1e-3 { 0.5 } else { v as f64 }).collect()
            }
        };
        let dy = normals(rng, 7);
        let analytic = unary::reference::unary_backward(&x, &dy, f);
        let loss = |v: &[Vec<f64>]| {
            dot(&v[0].iter().map(|&t| unary::reference::apply(f, t)).collect::<Vec<_>>(), &dy)
        };
        // Inputs up to 400 in size (log, sqrt, recip): a looser bound than the rows' 1e-8.
        checks.extend(differences_with(
            &format!("unary {f:?}"),
            &["dx"],
            &[x],
            vec![analytic],
            loss,
            1e-6,
            1e-6,
        ));
    }
    checks
}

fn binary_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (rows, w) = (s[0], s[1]);
    Binary::ALL
        .iter()
        .map(|&op| {
            // A row vector broadcast over the rows; divisors kept away from zero.
            let a = rng.normal_vec(rows * w);
            let b: Vec<f32> = rng
                .uniform_vec(w, 0.5, 2.0)
                .iter()
                .zip(rng.normal_vec(w))
                .map(|(m, s)| m * s.signum())
                .collect();
            let y = recorded(gpu, |rec| binary(rec, &upload(gpu, s, &a)?, &upload(gpu, &[w], &b)?, op))?;
            out(format!("{op:?}"), &y, binary::reference::binary(&a, s, &b, &[w], op).1)
        })
        .collect()
}

fn reduce_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let x = rng.normal_vec(s[0] * s[1]);
    let mut outs = Vec::new();
    for &op in Reduce::ALL {
        for axis in 0..2 {
            let y = recorded(gpu, |rec| reduce(rec, &upload(gpu, s, &x)?, axis, op))?;
            outs.push(out(format!("{op:?} axis {axis}"), &y, reduce::reference::reduce(&x, s, axis, op))?);
        }
    }
    Ok(outs)
}

fn softmax_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let x: Vec<f32> = rng.normal_vec(s[0] * s[1]).iter().map(|v| 6.0 * v).collect();
    let y = recorded(gpu, |rec| softmax(rec, &upload(gpu, s, &x)?))?;
    Ok(vec![out("rows", &y, softmax::reference::softmax(&x, s[1]))?])
}

/// Row indices into `rows` rows, `n` of them, with repeats.
fn indices(rows: usize, n: usize, rng: &mut Rng) -> Vec<u32> {
    (0..n).map(|_| rng.below(rows as u32)).collect()
}

fn gather_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let src = rng.normal_vec(s[0] * s[1]);
    let idx = indices(s[0], 2 * s[0] + 1, rng);
    let y = recorded(gpu, |rec| {
        gather(rec, &upload(gpu, s, &src)?, &Tensor::from_slice(gpu, &[idx.len()], &idx)?)
    })?;
    Ok(vec![out("rows", &y, gather::reference::gather(&src, s[1], &idx))?])
}

fn scatter_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let n = 2 * s[0] + 1;
    let src = rng.normal_vec(n * s[1]);
    let idx = indices(s[0], n, rng);
    let base = rng.normal_vec(s[0] * s[1]);
    let y = upload(gpu, s, &base)?;
    recorded(gpu, |rec| {
        scatter_add(rec, &upload(gpu, &[n, s[1]], &src)?, &Tensor::from_slice(gpu, &[n], &idx)?, &y)
    })?;
    Ok(vec![out("rows", &y, scatter_add::reference::scatter_add(&src, s[1], &idx, &base))?])
}

fn columns_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let src = rng.normal_vec(s[0] * s[1]);
    let (col, count) = (s[1] / 3, s[1] - s[1] / 3);
    let y = recorded(gpu, |rec| columns(rec, &upload(gpu, s, &src)?, col, count, -0.5))?;
    Ok(vec![out("slice", &y, columns::reference::columns(&src, s[1], col, count, -0.5))?])
}

fn cast_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    // Values of every magnitude f16 holds, subnormals and the rounding boundary included.
    // (Past f16's largest value 65504 both sides give infinity, which an NMSE cannot compare.)
    let x: Vec<f32> =
        rng.normal_vec(s[0]).iter().map(|v| v * 2f32.powi(((v * 8.0) as i32).clamp(-26, 12))).collect();
    let back = recorded(gpu, |rec| {
        let h = cast(rec, &upload(gpu, s, &x)?, DType::F16)?;
        cast(rec, &h, DType::F32)
    })?;
    Ok(vec![out("f32 -> f16 -> f32", &back, cast::reference::to_f16(&x))?])
}

fn concat_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let n = s[0];
    let src: Vec<u32> = (0..n + 3).map(|_| rng.next_u32()).collect();
    let dst: Vec<u32> = (0..2 * n + 5).map(|_| rng.next_u32()).collect();
    let t = Tensor::from_slice(gpu, &[dst.len()], &dst)?;
    // Past the end of u32 (wrapping), from and to offsets that are not multiples of anything.
    let add = u32::MAX - 7;
    recorded(gpu, |rec| {
        concat::copy_add(rec, &Tensor::from_slice(gpu, &[src.len()], &src)?, 2, &t, n + 1, n, add)
    })?;
    Ok(vec![out_u32("copy_add", &t, &concat::reference::copy_add(&src, 2, &dst, n + 1, n, add))?])
}

fn scan_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    // Large values, so that the sums wrap.
    let x: Vec<u32> = (0..s[0]).map(|_| rng.next_u32() >> 4).collect();
    let y = Tensor::empty(gpu, s, DType::U32)?;
    let total = recorded(gpu, |rec| exclusive_scan(rec, &Tensor::from_slice(gpu, s, &x)?, &y))?;
    let (want, want_total) = scan::reference::exclusive_scan(&x);
    Ok(vec![out_u32("prefix sums", &y, &want)?, out_u32("total", &total, &[want_total])?])
}

fn sort_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (n, bits) = (s[0], s[1] as u32);
    // Keys with bits above `bits` set (they must not change the order), many equal keys.
    let keys: Vec<u32> = (0..n).map(|_| rng.next_u32() & !(0xf << (bits.min(28)))).collect();
    let values: Vec<u32> = (0..n as u32).collect();
    let (k, v) = recorded(gpu, |rec| {
        sort_pairs(
            rec,
            &Tensor::from_slice(gpu, &[n], &keys)?,
            &Tensor::from_slice(gpu, &[n], &values)?,
            bits,
        )
    })?;
    let (want_k, want_v) = sort::reference::sort_pairs(&keys, &values, bits);
    Ok(vec![out_u32("keys", &k, &want_k)?, out_u32("values (stable)", &v, &want_v)?])
}

fn matmul_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (m, k, n) = (s[0], s[1], s[2]);
    let mut outs = Vec::new();
    for (ta, tb) in [(false, false), (true, false), (false, true)] {
        let sa = if ta { [k, m] } else { [m, k] };
        let sb = if tb { [n, k] } else { [k, n] };
        let (a, b) = (rng.normal_vec(m * k), rng.normal_vec(k * n));
        let y = recorded(gpu, |rec| matmul(rec, &upload(gpu, &sa, &a)?, &upload(gpu, &sb, &b)?, ta, tb))?;
        let (want, _) = matmul::reference::matmul(&f64s(&a), &sa, &f64s(&b), &sb, ta, tb)?;
        outs.push(out(format!("ta={ta} tb={tb}"), &y, want)?);
    }
    Ok(outs)
}

fn norm_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let x = rng.normal_vec(s[0]);
    let y = recorded(gpu, |rec| global_norm(rec, &upload(gpu, s, &x)?))?;
    let got: Vec<f32> = y.read()?;
    Ok(vec![Output {
        name: "norm".into(),
        got: vec![got[0] as f64],
        want: vec![norm::reference::global_norm(&x)],
    }])
}

fn rmsnorm_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (rows, w) = (s[0], s[1]);
    let (x, g, dy) = (rng.normal_vec(rows * w), rng.normal_vec(w), rng.normal_vec(rows * w));
    let eps = 1e-6;
    let (wt, dw) = (upload(gpu, &[w], &g)?, upload(gpu, &[w], &vec![0.0; w])?);
    let (y, dx) = recorded(gpu, |rec| {
        let xt = upload(gpu, s, &x)?;
        let (y, rstd) = rmsnorm(rec, &xt, &wt, eps)?;
        let dx = rmsnorm_backward(rec, &xt, &wt, &rstd, &upload(gpu, s, &dy)?, Some(&dw), None)?;
        Ok((y, dx))
    })?;
    let (want_y, _) = rmsnorm::reference::rmsnorm(&f64s(&x), &f64s(&g), eps as f64);
    let (want_dx, want_dw) =
        rmsnorm::reference::rmsnorm_backward(&f64s(&x), &f64s(&g), eps as f64, &f64s(&dy));
    Ok(vec![out("y", &y, want_y)?, out("dx", &dx, want_dx)?, out("dw", &dw, want_dw)?])
}

fn rmsnorm_gradients(rng: &mut Rng) -> Vec<Gradient> {
    let (n, width, eps) = (3, 5, 1e-5);
    let g = normals(rng, n * width);
    let inputs = vec![normals(rng, n * width), normals(rng, width)];
    let (dx, dw) = rmsnorm::reference::rmsnorm_backward(&inputs[0], &inputs[1], eps, &g);
    let loss = |v: &[Vec<f64>]| dot(&rmsnorm::reference::rmsnorm(&v[0], &v[1], eps).0, &g);
    against_differences("rmsnorm", &["dx", "dw"], &inputs, vec![dx, dw], loss)
}

fn layernorm_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (rows, w) = (s[0], s[1]);
    // An offset mean, as the layers see it.
    let x: Vec<f32> = rng.normal_vec(rows * w).iter().map(|v| v + 3.0).collect();
    let (g, b, dy) = (rng.normal_vec(w), rng.normal_vec(w), rng.normal_vec(rows * w));
    let eps = 1e-6;
    let zeros = vec![0.0; w];
    let (wt, bt, dw, db) = (
        upload(gpu, &[w], &g)?,
        upload(gpu, &[w], &b)?,
        upload(gpu, &[w], &zeros)?,
        upload(gpu, &[w], &zeros)?,
    );
    let (y, dx) = recorded(gpu, |rec| {
        let xt = upload(gpu, s, &x)?;
        let o = layernorm(rec, &xt, w, Some((&wt, &bt)), eps)?;
        let dx = layernorm_backward(
            rec,
            &xt,
            w,
            Some((&wt, &dw, &db)),
            &o.mean,
            &o.rstd,
            &upload(gpu, s, &dy)?,
            None,
        )?;
        Ok((o.y, dx))
    })?;
    let (gx, gg, gb) = (f64s(&x), f64s(&g), f64s(&b));
    let (want_y, _, _) = layernorm::reference::layernorm(&gx, w, Some((&gg, &gb)), eps as f64);
    let (want_dx, want_dw, want_db) =
        layernorm::reference::layernorm_backward(&gx, w, Some(&gg), eps as f64, &f64s(&dy));
    Ok(vec![
        out("y", &y, want_y)?,
        out("dx", &dx, want_dx)?,
        out("dw", &dw, want_dw)?,
        out("db", &db, want_db)?,
    ])
}

fn layernorm_gradients(rng: &mut Rng) -> Vec<Gradient> {
    let (n, width, eps) = (3, 5, 1e-5);
    let g = normals(rng, n * width);
    let inputs = vec![normals(rng, n * width), normals(rng, width), normals(rng, width)];
    let (dx, dw, db) = layernorm::reference::layernorm_backward(&inputs[0], width, Some(&inputs[1]), eps, &g);
    let loss =
        |v: &[Vec<f64>]| dot(&layernorm::reference::layernorm(&v[0], width, Some((&v[1], &v[2])), eps).0, &g);
    let mut checks =
        against_differences("layernorm affine", &["dx", "dw", "db"], &inputs, vec![dx, dw, db], loss);
    let (dx, _, _) = layernorm::reference::layernorm_backward(&inputs[0], width, None, eps, &g);
    let loss = |v: &[Vec<f64>]| dot(&layernorm::reference::layernorm(&v[0], width, None, eps).0, &g);
    checks.extend(against_differences("layernorm plain", &["dx"], &inputs[..1], vec![dx], loss));
    checks
}

fn swiglu_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let n = s[0] * s[1];
    let (a, b, dh) = (rng.normal_vec(n), rng.normal_vec(n), rng.normal_vec(n));
    let (h, (da, db)) = recorded(gpu, |rec| {
        let (at, bt) = (upload(gpu, s, &a)?, upload(gpu, s, &b)?);
        Ok((swiglu(rec, &at, &bt)?, swiglu_backward(rec, &at, &bt, &upload(gpu, s, &dh)?)?))
    })?;
    let (ga, gb) = (f64s(&a), f64s(&b));
    let (want_da, want_db) = swiglu::reference::swiglu_backward(&ga, &gb, &f64s(&dh));
    Ok(vec![
        out("h", &h, swiglu::reference::swiglu(&ga, &gb))?,
        out("da", &da, want_da)?,
        out("db", &db, want_db)?,
    ])
}

fn swiglu_gradients(rng: &mut Rng) -> Vec<Gradient> {
    let g = normals(rng, 9);
    let inputs = vec![normals(rng, 9), normals(rng, 9)];
    let (da, db) = swiglu::reference::swiglu_backward(&inputs[0], &inputs[1], &g);
    let loss = |v: &[Vec<f64>]| dot(&swiglu::reference::swiglu(&v[0], &v[1]), &g);
    against_differences("swiglu", &["da", "db"], &inputs, vec![da, db], loss)
}

fn adaln_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (b, t, d) = (s[0], s[1], s[2]);
    let (x, res, dy) = (rng.normal_vec(b * t * d), rng.normal_vec(b * t * d), rng.normal_vec(b * t * d));
    let (scale, shift, gate) = (rng.normal_vec(b * d), rng.normal_vec(b * d), rng.normal_vec(b * d));
    let (y, o, (ga_m, gp_m), (ga_g, gp_g)) = recorded(gpu, |rec| {
        let (xt, dyt) = (upload(gpu, &[b, t, d], &x)?, upload(gpu, &[b, t, d], &dy)?);
        let (sc, sh, gt) =
            (upload(gpu, &[b, d], &scale)?, upload(gpu, &[b, d], &shift)?, upload(gpu, &[b, d], &gate)?);
        let y = adaln::modulate(rec, &xt, &sc, &sh)?;
        let o = adaln::gate(rec, &y, &gt, &upload(gpu, &[b, t, d], &res)?)?;
        // The elementwise part of each backward: modulate's (one = 1) and the gate's (one = 0).
        let m = adaln::backward(rec, &xt, &sc, &dyt, 1.0)?;
        let g = adaln::backward(rec, &y, &gt, &dyt, 0.0)?;
        Ok((y, o, m, g))
    })?;
    let r = &adaln::reference::modulate(&f64s(&x), &f64s(&shift), &f64s(&scale), b, t, d);
    let want_o = adaln::reference::gated_residual(&f64s(&res), &f64s(&gate), r, b, t, d);
    // modulate's dx and the per-row dscale terms; the gate's dy and per-row dgate terms.
    let [dx, _, _] = adaln::reference::modulate_backward(&f64s(&x), &f64s(&scale), &f64s(&dy), b, t, d);
    let [_, _, dy_gate] = adaln::reference::gated_residual_backward(&f64s(&gate), r, &f64s(&dy), b, t, d);
    let times = |a: &[f64], c: &[f32]| a.iter().zip(c).map(|(p, q)| p * *q as f64).collect::<Vec<f64>>();
    Ok(vec![
        out("y", &y, r.clone())?,
        out("out", &o, want_o)?,
        out("dx", &ga_m, dx)?,
        out("dy x (dscale terms)", &gp_m, times(&f64s(&dy), &x))?,
        out("dy (gate)", &ga_g, dy_gate)?,
        out("dout y (dgate terms)", &gp_g, times(r, &dy))?,
    ])
}

fn adaln_gradients(rng: &mut Rng) -> Vec<Gradient> {
    use adaln::reference as r;
    let (b, t, d) = (2, 3, 4);
    let g = normals(rng, b * t * d);
    let inputs = vec![normals(rng, b * t * d), normals(rng, b * d), normals(rng, b * d)];
    let [dx, dshift, dscale] = r::modulate_backward(&inputs[0], &inputs[2], &g, b, t, d);
    let loss = |v: &[Vec<f64>]| dot(&r::modulate(&v[0], &v[1], &v[2], b, t, d), &g);
    let mut checks = against_differences(
        "adaln modulate",
        &["dx", "dshift", "dscale"],
        &inputs,
        vec![dx, dshift, dscale],
        loss,
    );
    let inputs = vec![normals(rng, b * t * d), normals(rng, b * d), normals(rng, b * t * d)];
    let [dres, dgate, dy] = r::gated_residual_backward(&inputs[1], &inputs[2], &g, b, t, d);
    let loss = |v: &[Vec<f64>]| dot(&r::gated_residual(&v[0], &v[1], &v[2], b, t, d), &g);
    checks.extend(against_differences(
        "adaln gate",
        &["dres", "dgate", "dy"],
        &inputs,
        vec![dres, dgate, dy],
        loss,
    ));
    checks
}

fn fourier_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (rows, c, f) = (s[0], s[1], s[2]);
    let x = rng.uniform_vec(rows * c, -1.0, 1.0);
    let freq: Vec<f32> = (0..f).map(|i| 2f32.powi(i as i32) * std::f32::consts::PI).collect();
    let mut outs = Vec::new();
    for include_input in [false, true] {
        let width = fourier_width(c, f, include_input);
        let dy = rng.normal_vec(rows * width);
        let (y, dx) = recorded(gpu, |rec| {
            let (xt, ft) = (upload(gpu, &[rows, c], &x)?, upload(gpu, &[f], &freq)?);
            let y = fourier(rec, &xt, &ft, include_input)?;
            Ok((y, fourier_backward(rec, &xt, &ft, include_input, &upload(gpu, &[rows, width], &dy)?)?))
        })?;
        let (gx, gf) = (f64s(&x), f64s(&freq));
        outs.push(out(
            format!("y input={include_input}"),
            &y,
            fourier::reference::fourier(&gx, c, &gf, include_input),
        )?);
        let want_dx = fourier::reference::fourier_backward(&gx, c, &gf, include_input, &f64s(&dy));
        outs.push(out(format!("dx input={include_input}"), &dx, want_dx)?);
    }
    Ok(outs)
}

fn fourier_gradients(rng: &mut Rng) -> Vec<Gradient> {
    // Frequencies up to 2^12: the third derivative grows as (pi 2^12)^3, so a smaller step keeps
    // the truncation error of the central difference down.
    let (n, c) = (2, 3);
    let freqs: Vec<f64> = (0..6).map(|f| (12.0 * f as f64 / 5.0).exp2()).collect();
    let mut checks = Vec::new();
    for include in [false, true] {
        let width = c * 2 * freqs.len() + if include { c } else { 0 };
        let g = normals(rng, n * width);
        let inputs = vec![(0..n * c).map(|_| rng.range(-1.0, 1.0)).collect::<Vec<f64>>()];
        let dx = fourier::reference::fourier_backward(&inputs[0], c, &freqs, include, &g);
        let loss = |v: &[Vec<f64>]| dot(&fourier::reference::fourier(&v[0], c, &freqs, include), &g);
        checks.extend(differences_with(
            &format!("fourier input={include}"),
            &["dx"],
            &inputs,
            vec![dx],
            loss,
            1e-9,
            2e-7,
        ));
    }
    checks
}

fn loss_target(kind: LossKind, n: usize, rng: &mut Rng) -> Vec<f32> {
    match kind {
        LossKind::BceWithLogits | LossKind::Focal { .. } => rng.uniform_vec(n, 0.0, 1.0),
        _ => rng.normal_vec(n),
    }
}

fn loss_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let n = s[0];
    let pred = rng.normal_vec(n);
    let mut outs = Vec::new();
    for &kind in LOSS_KINDS {
        let target = loss_target(kind, n, rng);
        let (value, grad) =
            recorded(gpu, |rec| loss(rec, kind, &upload(gpu, s, &pred)?, &upload(gpu, s, &target)?, 0.75))?;
        let (want_value, want_grad) = loss::reference::loss(kind, &f64s(&pred), &f64s(&target), 0.75);
        outs.push(out(format!("{kind:?} value"), &value, vec![want_value])?);
        outs.push(out(format!("{kind:?} grad"), &grad, want_grad)?);
    }
    Ok(outs)
}

fn loss_gradients(rng: &mut Rng) -> Vec<Gradient> {
    let mut checks = Vec::new();
    // Every kind, and the focal loss at gamma 1 and 3 too; labels soft and hard (0 or 1).
    let kinds =
        LOSS_KINDS.iter().copied().chain([LossKind::Focal { gamma: 1.0 }, LossKind::Focal { gamma: 3.0 }]);
    for kind in kinds {
        let pred: Vec<f64> = normals(rng, 8).iter().map(|v| 2.0 * v).collect();
        let mut target = f64s(&loss_target(kind, 8, rng));
        if matches!(kind, LossKind::BceWithLogits | LossKind::Focal { .. }) {
            target[..4].iter_mut().enumerate().for_each(|(i, t)| *t = (i % 2) as f64);
        }
        let (_, grad) = loss::reference::loss(kind, &pred, &target, 0.75);
        let loss = |v: &[Vec<f64>]| loss::reference::loss(kind, &v[0], &target, 0.75).0;
        checks.extend(against_differences(&format!("loss {kind:?}"), &["dpred"], &[pred], vec![grad], loss));
    }
    checks
}

fn attention_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (nq, nk, h, d) = (s[0], s[1], s[2], s[3]);
    let scale = 1.0 / (d as f32).sqrt();
    let (q, k, v) = (rng.normal_vec(nq * h * d), rng.normal_vec(nk * h * d), rng.normal_vec(nk * h * d));
    let d_o = rng.normal_vec(nq * h * d);
    // Two segments: the first half of the queries reads the first third of the keys.
    let (q_lens, k_lens) = if nq > 1 && nk > 1 {
        (vec![nq / 2, nq - nq / 2], vec![nk / 3, nk - nk / 3])
    } else {
        (vec![nq], vec![nk])
    };
    let seg = Segments::from_lengths(gpu, &q_lens, &k_lens)?;
    let (o, grads) = recorded(gpu, |rec| {
        let (qt, kt, vt) =
            (upload(gpu, &[nq, h, d], &q)?, upload(gpu, &[nk, h, d], &k)?, upload(gpu, &[nk, h, d], &v)?);
        let o = attention(rec, &qt, &kt, &vt, &seg, scale)?;
        let grads =
            attention_backward(rec, &qt, &kt, &vt, &o, &upload(gpu, &[nq, h, d], &d_o)?, &seg, scale)?;
        Ok((o, grads))
    })?;
    let (q_off, k_off) = (attention::reference::offsets(&q_lens), attention::reference::offsets(&k_lens));
    let (gq, gk, gv) = (f64s(&q), f64s(&k), f64s(&v));
    let (want_o, _) = attention::reference::attention(&gq, &gk, &gv, &q_off, &k_off, h, d, scale as f64);
    let (dq, dk, dv) = attention::reference::attention_backward(
        &gq,
        &gk,
        &gv,
        &f64s(&d_o),
        &q_off,
        &k_off,
        h,
        d,
        scale as f64,
    );
    Ok(vec![
        out("o", &o.o, want_o)?,
        out("dq", &grads.dq, dq)?,
        out("dk", &grads.dk, dk)?,
        out("dv", &grads.dv, dv)?,
    ])
}

fn attention_gradients(rng: &mut Rng) -> Vec<Gradient> {
    use attention::reference as r;
    // Two segments of 2 and 3 queries over 3 and 2 keys, 2 heads of width 3.
    let (h, d, scale) = (2, 3, 0.6);
    let (q_off, k_off) = (r::offsets(&[2, 3]), r::offsets(&[3, 2]));
    let g = normals(rng, 5 * h * d);
    let inputs = vec![normals(rng, 5 * h * d), normals(rng, 5 * h * d), normals(rng, 5 * h * d)];
    let (dq, dk, dv) =
        r::attention_backward(&inputs[0], &inputs[1], &inputs[2], &g, &q_off, &k_off, h, d, scale);
    let loss = |v: &[Vec<f64>]| dot(&r::attention(&v[0], &v[1], &v[2], &q_off, &k_off, h, d, scale).0, &g);
    against_differences("attention", &["dq", "dk", "dv"], &inputs, vec![dq, dk, dv], loss)
}

const HEAD_RANGE: HeadRange = HeadRange { offset_range: 0.05, scale_min: 0.001, scale_max: 0.01 };

fn gaussian_head_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (v, per) = (s[0], s[1]);
    let m = v * per;
    let raw: Vec<f32> = rng.normal_vec(m * gaussian_head::RAW).iter().map(|x| 3.0 * x).collect();
    let centres = rng.uniform_vec(v * 3, -1.0, 1.0);
    let widths = [3, 3, 4, 1, 3];
    let grads: Vec<Vec<f32>> = widths.iter().map(|w| rng.normal_vec(m * w)).collect();
    let (fwd, d_raw) = recorded(gpu, |rec| {
        let (rt, ct) = (upload(gpu, &[m, gaussian_head::RAW], &raw)?, upload(gpu, &[v, 3], &centres)?);
        let fwd = head_forward(rec, &rt, &ct, &HEAD_RANGE)?;
        let shape = |w: usize| if w == 1 { vec![m] } else { vec![m, w] };
        let t = |i: usize| upload(gpu, &shape(widths[i]), &grads[i]);
        let d =
            GaussianSet { means: t(0)?, log_scales: t(1)?, quats: t(2)?, opacities: t(3)?, colours: t(4)? };
        Ok((fwd, head_backward(rec, &rt, &ct, &HEAD_RANGE, &d)?))
    })?;
    let (graw, gc) = (f64s(&raw), f64s(&centres));
    let want = gaussian_head::reference::head(&graw, &gc, per, &HEAD_RANGE);
    let d: [Vec<f64>; 5] = std::array::from_fn(|i| f64s(&grads[i]));
    let mut outs = Vec::new();
    for (i, (name, t)) in
        ["means", "log_scales", "quats", "logits", "colours"].iter().zip(fwd.fields()).enumerate()
    {
        outs.push(out(*name, t, want[i].clone())?);
    }
    outs.push(out("d raw", &d_raw, gaussian_head::reference::head_backward(&graw, &d, &HEAD_RANGE))?);
    Ok(outs)
}

fn gaussian_head_gradients(rng: &mut Rng) -> Vec<Gradient> {
    let (v, per) = (2, 3);
    let m = v * per;
    let raw = normals(rng, m * gaussian_head::RAW);
    let centres = normals(rng, v * 3);
    let d: [Vec<f64>; 5] = std::array::from_fn(|i| normals(rng, m * [3, 3, 4, 1, 3][i]));
    let analytic = gaussian_head::reference::head_backward(&raw, &d, &HEAD_RANGE);
    let loss = |x: &[Vec<f64>]| {
        let o = gaussian_head::reference::head(&x[0], &centres, per, &HEAD_RANGE);
        (0..5).map(|i| dot(&o[i], &d[i])).sum()
    };
    against_differences("gaussian_head", &["d raw"], &[raw], vec![analytic], loss)
}

fn voxel_head_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (cells, per, h) = (s[0], s[1], s[2]);
    let mut outs = Vec::new();
    for directions in [false, true] {
        let f = if directions { 4 * h } else { h };
        let (feat, emb, off) = (rng.normal_vec(cells * f), rng.normal_vec(per * h), rng.normal_vec(per * 3));
        let dpre = rng.normal_vec(cells * per * h);
        let (pre, act, d) = recorded(gpu, |rec| {
            let (tf, te, to) = (
                upload(gpu, &[cells, f], &feat)?,
                upload(gpu, &[per, h], &emb)?,
                upload(gpu, &[per, 3], &off)?,
            );
            let (pre, act) = voxel_head::forward(rec, &tf, &te, &to, directions)?;
            let d =
                voxel_head::backward(rec, &tf, &te, &to, directions, &upload(gpu, &[cells, per, h], &dpre)?)?;
            Ok((pre, act, d))
        })?;
        let want = voxel_head::reference::pre(&f64s(&feat), &f64s(&emb), &f64s(&off), h, directions);
        let gelu: Vec<f64> = want.iter().map(|&x| unary::reference::apply(Unary::Gelu, x)).collect();
        let dwant = voxel_head::reference::pre_backward(&f64s(&off), &f64s(&dpre), cells, h, directions);
        outs.push(out(format!("pre directions={directions}"), &pre, want)?);
        outs.push(out(format!("gelu directions={directions}"), &act, gelu)?);
        outs.push(out(format!("d features directions={directions}"), &d, dwant)?);
    }
    Ok(outs)
}

fn voxel_head_gradients(rng: &mut Rng) -> Vec<Gradient> {
    let (cells, per, h) = (2, 3, 2);
    let mut checks = Vec::new();
    for directions in [false, true] {
        let f = if directions { 4 * h } else { h };
        let (emb, off, dpre) = (normals(rng, per * h), normals(rng, per * 3), normals(rng, cells * per * h));
        let features = normals(rng, cells * f);
        let analytic = voxel_head::reference::pre_backward(&off, &dpre, cells, h, directions);
        let loss = |x: &[Vec<f64>]| dot(&voxel_head::reference::pre(&x[0], &emb, &off, h, directions), &dpre);
        checks.extend(against_differences(
            &format!("voxel_head directions={directions}"),
            &["d features"],
            &[features],
            vec![analytic],
            loss,
        ));
    }
    checks
}

fn adamw_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let n = s[0];
    let (p0, g) = (rng.normal_vec(n), rng.normal_vec(n));
    let (m0, v0): (Vec<f32>, Vec<f32>) = (rng.normal_vec(n), rng.uniform_vec(n, 0.0, 2.0));
    let cfg = AdamWConfig { weight_decay: 0.1, ..AdamWConfig::default() };
    // Clipping on (a norm of 3 over a limit of 1), a third of the elements without decay.
    let step = AdamWStep { lr: 1e-2, step: 5, grad_scale: 0.5, max_norm: Some(1.0) };
    let (p, m, v) = (upload(gpu, s, &p0)?, upload(gpu, s, &m0)?, upload(gpu, s, &v0)?);
    let norm = upload(gpu, &[1], &[3.0])?;
    let decay_len = 2 * n / 3;
    recorded(gpu, |rec| {
        let t = AdamWTensors {
            params: &p,
            grads: &upload(gpu, s, &g)?,
            m: &m,
            v: &v,
            decay_len,
            norm: Some(&norm),
        };
        adamw(rec, &t, &cfg, &step)
    })?;
    let (mut wp, mut wm, mut wv) = (f64s(&p0), f64s(&m0), f64s(&v0));
    assert!(adamw::reference::adamw(&mut wp, &mut wm, &mut wv, &g, decay_len, Some(3.0), &cfg, &step));
    Ok(vec![out("params", &p, wp)?, out("m", &m, wm)?, out("v", &v, wv)?])
}

/// Rows on a grid of eighths in [-1, 1]: every squared distance is exact in f32 and f64, so
/// ties are real ties and the kernels must break them as the reference does.
fn grid_points(rng: &mut Rng, n: usize) -> Vec<f32> {
    (0..4 * n).map(|_| (rng.below(17) as f32 - 8.0) / 8.0).collect()
}

fn assign_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (n, k) = (s[0], s[1]);
    let (points, queries) = (grid_points(rng, n), grid_points(rng, k));
    let ids = recorded(gpu, |rec| {
        assign_nearest(rec, &upload(gpu, &[n, 4], &points)?, &upload(gpu, &[k, 4], &queries)?)
    })?;
    Ok(vec![out_u32("nearest query", &ids, &assign::reference::assign_nearest(&points, &queries))?])
}

fn fps_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let n = s[0];
    // Grid points: exact distances, many ties; a quarter of them chosen.
    let points = grid_points(rng, n);
    let candidates = fps::random_candidates(n, n, rng)?;
    let k = n.div_ceil(4);
    let chosen = recorded(gpu, |rec| fps(rec, &upload(gpu, &[n, 4], &points)?, &candidates, k))?;
    Ok(vec![out_u32("chosen", &chosen, &fps::reference::fps(&points, &candidates, k))?])
}

/// A jittered square sheet of `side` x `side` particles 0.03 apart, one corner pinned, dropped
/// just above the ground so that it lands, slides, bounces (restitution 0.3) and folds onto
/// itself (self-collision between particles 0.04 apart), against the f64 reference's substeps.
fn cloth_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let side = s[0];
    let h = 0.03f32;
    let c = (side - 1) as f32 * h / 2.0;
    let points: Vec<[f32; 3]> = (0..side * side)
        .map(|i| {
            let jitter = |rng: &mut Rng| rng.range(-0.008, 0.008) as f32;
            [
                (i % side) as f32 * h - c + jitter(rng),
                -0.972 + jitter(rng),
                (i / side) as f32 * h - c + jitter(rng),
            ]
        })
        .collect();
    let mut mesh = ClothMesh::from_triangles(points, &ClothMesh::grid_triangles(side), 1e-6, 1e-3)?;
    mesh.inv_mass[0] = 0.0;
    let params =
        ClothParams { substeps: 4, restitution: 0.3, radius: 0.02, exclude: 0.035, ..ClothParams::default() };
    let frames = 4;
    let mut state = cloth::reference::State::new(&mesh);
    for _ in 0..frames * params.substeps {
        cloth::reference::substep(&mut state, &mesh, &params, 0.01 / params.substeps as f64);
    }
    let mut sim = ClothSim::new(gpu, &mesh, params)?;
    for _ in 0..frames {
        sim.step(gpu, 0.01)?;
    }
    let got: Vec<f64> = sim.positions()?.iter().map(|&v| v as f64).collect();
    let want: Vec<f64> = state.x.iter().flatten().copied().collect();
    Ok(vec![Output { name: "positions".into(), got, want }])
}

fn window_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let n = s[0];
    // Points inside and outside the grid (clamped to its border cells), over 24 frames.
    let points: Vec<f32> = (0..n)
        .flat_map(|_| {
            let t = rng.below(24) as f32;
            [rng.range(-1.2, 1.2) as f32, rng.range(-1.2, 1.2) as f32, rng.range(-1.2, 1.2) as f32, t]
        })
        .collect();
    let grid = WindowGrid::new([-1.0, -1.0, -1.0, 0.0], [1.0, 1.0, 1.0, 24.0], [0.5, 0.5, 0.5, 6.0])?;
    let mut outs = Vec::new();
    for (what, grid) in [("", grid), (" shifted", grid.shifted())] {
        let (ids, groups) = recorded(gpu, |rec| {
            let ids = window_ids(rec, &upload(gpu, &[n, 4], &points)?, &grid)?;
            let groups = group_by_window(rec, &ids, grid.num_windows())?;
            Ok((ids, groups))
        })?;
        let want_ids = window::reference::window_ids(&points, &grid);
        let (order, offsets, segment_ids) = window::reference::group_by_window(&want_ids);
        let count = groups.read_count()? as usize;
        let head = |t: &Tensor, len: usize| -> Result<Tensor> { t.view(0, &[len]) };
        outs.push(out_u32(format!("ids{what}"), &ids, &want_ids)?);
        outs.push(out_u32(format!("order{what}"), &groups.order, &order)?);
        outs.push(out_u32(format!("offsets{what}"), &head(&groups.offsets, count + 1)?, &offsets)?);
        outs.push(out_u32(format!("segment ids{what}"), &head(&groups.segment_ids, count)?, &segment_ids)?);
    }
    Ok(outs)
}

const RASTER_BG: [f32; 3] = [0.1, 0.2, 0.3];

/// The camera of the raster rows: looking at the scene from off its axis, at a size that is
/// not a multiple of the tile.
fn raster_camera(w: u32, h: u32) -> Camera {
    Camera::look_at([0.5, -0.3, -0.5], [0.0, 0.0, 3.0], [0.0, -1.0, 0.0], 50.0, w, h)
}

fn raster_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let (n, w, h) = (s[0], s[1] as u32, s[2] as u32);
    let cam = raster_camera(w, h);
    let data = random_gaussians(n, rng.next_u32() as u64, (-3.0, -1.0), (-1.0, 3.0));
    let px = (w * h) as usize;
    let (dr, da, dd) = (rng.normal_vec(3 * px), rng.normal_vec(px), rng.uniform_vec(px, -0.1, 0.1));
    let g = data.upload(gpu)?;
    let rendered = raster::render(gpu, &g, &cam, RASTER_BG)?;
    let grads = recorded(gpu, |rec| {
        let (hh, ww) = (h as usize, w as usize);
        let (tr, ta, td) =
            (upload(gpu, &[hh, ww, 3], &dr)?, upload(gpu, &[hh, ww], &da)?, upload(gpu, &[hh, ww], &dd)?);
        raster::render_backward_with(rec, BackwardKernel::Ordered, &g, &rendered, &tr, &ta, &td)
    })?;
    let scene = raster::reference::Scene::from_data(&data);
    let image = raster::reference::render(&scene, &cam, RASTER_BG);
    let want =
        raster::reference::render_backward(&scene, &cam, RASTER_BG, &f64s(&dr), &f64s(&da), &f64s(&dd));
    let img = &rendered.image;
    let mut outs = vec![
        out("rgb", &img.rgb, image.rgb)?,
        out("alpha", &img.alpha, image.alpha)?,
        out("depth", &img.depth, image.depth)?,
    ];
    let wanted = [want.means, want.log_scales, want.quats, want.opacities, want.colours];
    for ((name, t), want) in
        ["d means", "d log_scales", "d quats", "d logits", "d colours"].iter().zip(grads.fields()).zip(wanted)
    {
        outs.push(out(*name, t, want)?);
    }
    Ok(outs)
}

/// Four Gaussians, every one drawn, a camera off the axis.
fn raster_gradients(rng: &mut Rng) -> Vec<Gradient> {
    use raster::reference as r;
    let cam = Camera::look_at([0.2, 0.1, -0.3], [0.0, 0.0, 3.0], [0.0, -1.0, 0.0], 55.0, 32, 32);
    let data = random_gaussians(4, rng.next_u32() as u64, (-2.5, -1.8), (-1.0, 1.0));
    let base = r::Scene::from_data(&data);
    assert_eq!(r::project(&base, &cam).1[0], 4, "every Gaussian of the gradient check is drawn");
    let px = 32 * 32;
    let (dr, da, dd) = (normals(rng, 3 * px), normals(rng, px), normals(rng, px));
    let g = r::render_backward(&base, &cam, RASTER_BG, &dr, &da, &dd);
    let inputs = vec![
        base.means.clone(),
        base.log_scales.clone(),
        base.quats.clone(),
        base.opacities.clone(),
        base.colours.clone(),
    ];
    let loss = |v: &[Vec<f64>]| {
        let scene = r::Scene {
            means: v[0].clone(),
            log_scales: v[1].clone(),
            quats: v[2].clone(),
            opacities: v[3].clone(),
            colours: v[4].clone(),
        };
        let img = r::render(&scene, &cam, RASTER_BG);
        dot(&img.rgb, &dr) + dot(&img.alpha, &da) + dot(&img.depth, &dd)
    };
    let names = ["d means", "d log_scales", "d quats", "d logits", "d colours"];
    against_differences(
        "raster",
        &names,
        &inputs,
        vec![g.means, g.log_scales, g.quats, g.opacities, g.colours],
        loss,
    )
}
