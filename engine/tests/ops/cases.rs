//! The op-case harness: every op that has an f64 reference, run forward and (where it has one)
//! backward at several shapes, each output held to the bound of one table. A case is a row of
//! [`CASES`]: the op, its shapes, and a function that runs it on random inputs and returns its
//! outputs beside the reference's. `VELOX_TEST_VERBOSE=1` prints every case's NMSE against its
//! bound; a failure lists every case over its bound, not just the first.
//!
//! The op families' own test files keep what a table row cannot say: edge cases (empty
//! tensors, more workgroups than one dispatch dimension takes, bindings past the limit),
//! pointwise bounds, f16 paths, determinism and the errors of bad input.

use crate::common;
use common::*;
use velox_engine::ops::attention::{self, attention, attention_backward, Segments};
use velox_engine::ops::binary::{self, binary, Binary};
use velox_engine::ops::columns::{self, columns};
use velox_engine::ops::fourier::{self, fourier, fourier_backward, fourier_width};
use velox_engine::ops::gather::{self, gather};
use velox_engine::ops::gelu::{self, gelu_backward};
use velox_engine::ops::layernorm::{self, layernorm, layernorm_backward};
use velox_engine::ops::loss::{self, loss, LossKind};
use velox_engine::ops::matmul::{self, matmul};
use velox_engine::ops::norm::{self, global_norm};
use velox_engine::ops::reduce::{self, reduce, Reduce};
use velox_engine::ops::rmsnorm::{self, rmsnorm, rmsnorm_backward};
use velox_engine::ops::scatter_add::{self, scatter_add};
use velox_engine::ops::softmax::{self, softmax};
use velox_engine::ops::swiglu::{self, swiglu, swiglu_backward};
use velox_engine::ops::unary::{self, unary, Unary};
use velox_engine::{Recorder, Result};

/// NMSE bounds against the f64 reference, one per op (forward and backward alike). The f32
/// ops round once per value or sum in f32 over at most a few thousand terms: their NMSE sits
/// near 1e-14 to 1e-12 on lavapipe; the bounds leave two orders of magnitude for devices that
/// round their builtins (exp, division, rsqrt) as loosely as Vulkan allows.
const BOUNDS: &[(&str, f64)] = &[
    ("unary", 1e-9),
    ("binary", 1e-12),
    ("reduce", 1e-10),
    ("softmax", 1e-10),
    ("gather", 0.0),
    ("scatter_add", 1e-12),
    ("columns", 1e-14),
    ("matmul", 1e-10),
    ("global_norm", 1e-12),
    ("rmsnorm", 1e-10),
    ("layernorm", 1e-10),
    ("swiglu", 1e-10),
    ("gelu_backward", 1e-10),
    // sin(f x) with f x rounded to f32 first: at the top octave (f = 512 pi, |x| <= 1) the
    // argument is off by up to 1608 * 6e-8 = 1e-4 radians, an NMSE near 1e-9 (measured 7e-10
    // forward, 5e-9 backward, whose rows carry a factor f).
    ("fourier", 1e-8),
    ("loss", 1e-10),
    ("attention", 1e-10),
];

/// One output of a case beside its reference.
struct Output {
    name: String,
    got: Vec<f32>,
    want: Vec<f64>,
}

fn out(name: impl Into<String>, got: &Tensor, want: Vec<f64>) -> Result<Output> {
    Ok(Output { name: name.into(), got: got.read()?, want })
}

type Run = fn(&Gpu, &[usize], &mut Rng) -> Result<Vec<Output>>;

/// An op at its shapes.
struct Case {
    op: &'static str,
    shapes: &'static [&'static [usize]],
    run: Run,
}

/// Rows by width: one row and one column, sizes off every power of two, and one past a
/// workgroup of 256.
const ROWS: &[&[usize]] = &[&[1, 1], &[3, 7], &[17, 64], &[65, 255], &[257, 130]];
/// Rows of the normalisations: a width of one normalises every row to +-w, and its gradient is
/// a difference of two nearly equal terms (relative error 1e-4 in f32 whatever the kernel), so
/// the narrowest rows here have five values.
const NORM_ROWS: &[&[usize]] = &[&[1, 5], &[3, 7], &[17, 64], &[65, 255], &[257, 130]];
/// Flat lengths.
const FLAT: &[&[usize]] = &[&[1], &[255], &[257], &[10_007]];

const CASES: &[Case] = &[
    Case { op: "unary", shapes: FLAT, run: unary_case },
    Case { op: "binary", shapes: ROWS, run: binary_case },
    Case { op: "reduce", shapes: ROWS, run: reduce_case },
    Case { op: "softmax", shapes: ROWS, run: softmax_case },
    Case { op: "gather", shapes: ROWS, run: gather_case },
    Case { op: "scatter_add", shapes: ROWS, run: scatter_case },
    Case { op: "columns", shapes: ROWS, run: columns_case },
    // [m, k, n]
    Case {
        op: "matmul",
        shapes: &[&[1, 1, 1], &[3, 7, 5], &[65, 130, 33], &[128, 64, 257]],
        run: matmul_case,
    },
    Case { op: "global_norm", shapes: FLAT, run: norm_case },
    Case { op: "rmsnorm", shapes: NORM_ROWS, run: rmsnorm_case },
    Case { op: "layernorm", shapes: NORM_ROWS, run: layernorm_case },
    Case { op: "swiglu", shapes: ROWS, run: swiglu_case },
    Case { op: "gelu_backward", shapes: ROWS, run: gelu_case },
    // [rows, channels, frequencies]
    Case { op: "fourier", shapes: &[&[1, 1, 1], &[17, 3, 6], &[257, 4, 10]], run: fourier_case },
    Case { op: "loss", shapes: FLAT, run: loss_case },
    // [queries, keys, heads, head width]
    Case {
        op: "attention",
        shapes: &[&[1, 1, 1, 16], &[17, 33, 2, 32], &[70, 65, 3, 64]],
        run: attention_case,
    },
];

fn bound(op: &str) -> f64 {
    BOUNDS.iter().find(|(o, _)| *o == op).unwrap_or_else(|| panic!("no bound for {op}")).1
}

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

#[test]
fn every_op_matches_its_reference_at_every_shape() {
    let gpu = gpu();
    let mut rng = Rng::new(2024);
    let (mut rows, mut over) = (Vec::new(), Vec::new());
    for case in CASES {
        let b = bound(case.op);
        for shape in case.shapes {
            let outputs =
                (case.run)(&gpu, shape, &mut rng).unwrap_or_else(|e| panic!("{} at {shape:?}: {e}", case.op));
            for o in outputs {
                assert_eq!(o.got.len(), o.want.len(), "{} {} at {shape:?}: lengths", case.op, o.name);
                let e = nmse(&o.got, &o.want);
                let row = format!(
                    "{:<14} {:<22} {:<18} nmse {e:9.2e}  bound {b:7.0e}",
                    case.op,
                    o.name,
                    format!("{shape:?}")
                );
                if e.is_nan() || e > b {
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
    assert!(rows.len() >= 100, "{} cases ran", rows.len());
}

#[test]
fn every_op_of_the_table_has_one_bound() {
    for case in CASES {
        assert_eq!(BOUNDS.iter().filter(|(o, _)| *o == case.op).count(), 1, "{}", case.op);
    }
    for (op, _) in BOUNDS {
        assert!(CASES.iter().any(|c| c.op == *op), "bound for {op} without a case");
    }
}

/// Inputs where every unary map is finite and well conditioned.
fn unary_input(f: Unary, n: usize, rng: &mut Rng) -> Vec<f32> {
    match f {
        Unary::Log | Unary::Sqrt | Unary::Rsqrt => rng.uniform_vec(n, 1e-3, 100.0),
        Unary::Recip => rng.uniform_vec(n, 0.1, 10.0),
        Unary::Exp => rng.uniform_vec(n, -20.0, 20.0),
        _ => rng.normal_vec(n).iter().map(|v| 4.0 * v).collect(),
    }
}

fn unary_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    Unary::ALL
        .iter()
        .map(|&f| {
            let x = unary_input(f, s[0], rng);
            let y = recorded(gpu, |rec| unary(rec, &upload(gpu, s, &x)?, f))?;
            out(format!("{f:?}"), &y, unary::reference::unary(&x, f))
        })
        .collect()
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
    for op in [Reduce::Sum, Reduce::Mean, Reduce::Max] {
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
        got: got[..1].to_vec(),
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

fn gelu_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let n = s[0] * s[1];
    let (x, dy) = (rng.normal_vec(n).iter().map(|v| 3.0 * v).collect::<Vec<f32>>(), rng.normal_vec(n));
    let dx = recorded(gpu, |rec| gelu_backward(rec, &upload(gpu, s, &x)?, &upload(gpu, s, &dy)?))?;
    Ok(vec![out("dx", &dx, gelu::reference::gelu_backward(&f64s(&x), &f64s(&dy)))?])
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

fn loss_case(gpu: &Gpu, s: &[usize], rng: &mut Rng) -> Result<Vec<Output>> {
    let n = s[0];
    let pred = rng.normal_vec(n);
    let mut outs = Vec::new();
    for kind in [LossKind::Mse, LossKind::L1, LossKind::Huber { delta: 0.5 }, LossKind::BceWithLogits] {
        let target = match kind {
            LossKind::BceWithLogits => rng.uniform_vec(n, 0.0, 1.0),
            _ => rng.normal_vec(n),
        };
        let (value, grad) =
            recorded(gpu, |rec| loss(rec, kind, &upload(gpu, s, &pred)?, &upload(gpu, s, &target)?, 0.75))?;
        let (want_value, want_grad) = loss::reference::loss(kind, &f64s(&pred), &f64s(&target), 0.75);
        outs.push(out(format!("{kind:?} value"), &value, vec![want_value])?);
        outs.push(out(format!("{kind:?} grad"), &grad, want_grad)?);
    }
    Ok(outs)
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
