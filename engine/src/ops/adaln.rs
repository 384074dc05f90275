//! adaLN modulation, fused (DiT's adaLN-Zero): `x [B, T, D]` with per-sample `[B, D]` shift,
//! scale and gate broadcast over each sample's T rows. Kernel: `shaders/adaln.wgsl`.
//!
//! - [`modulate`]: `y = x * (1 + scale) + shift` in one pass;
//! - [`gate`]: `out = res + gate * y` in one pass;
//! - [`backward`]: `ga = dy * (one + p)` and `gp = dy * a` in one pass, the elementwise part of
//!   both backward passes (`one` = 1: modulate's `dx` and `dy * x`; `one` = 0: the gate's
//!   `dy` and `dout * y`); the per-sample gradients are `gp` (and `dy`) summed over T, which
//!   is `gp` itself when T = 1 (a per-point modulation, as the surface decoder trains with).
//!
//! Tests: the harness (`engine/tests/ops/cases.rs`: both passes and the backward against the
//! reference, the reference against finite differences) and the layers built on it
//! (`tests/models/layers.rs`).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{ADALN_BACKWARD, ADALN_GATE, ADALN_MODULATE};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::fit_u32;
use crate::kernels::params::AdalnParams as Params;

/// Checks `x [B, T, D]` against per-sample tensors `[B, D]` and full-size ones.
fn check(what: &str, x: &Tensor, per_sample: &[&Tensor], full: &[&Tensor]) -> Result<Params> {
    let xs = x.shape();
    let bad = x.dtype() != DType::F32
        || xs.len() != 3
        || per_sample.iter().any(|s| s.dtype() != DType::F32 || s.shape() != [xs[0], xs[2]])
        || full.iter().any(|f| f.dtype() != DType::F32 || f.shape() != xs);
    if bad {
        return Err(Error::Shape(format!(
            "{what}: needs f32 x [B, T, D], per-sample [B, D] and full-size tensors like x; got x {x:?}, \
             per sample {per_sample:?}, full {full:?}"
        )));
    }
    let fit = |v: usize| fit_u32(v, || format!("{what} of {x:?}"));
    Ok(Params { n: fit(x.numel())?, t: fit(xs[1])?, d: fit(xs[2])?, one: 0.0 })
}

/// `y = x * (1 + scale) + shift`.
pub fn modulate(rec: &mut Recorder, x: &Tensor, scale: &Tensor, shift: &Tensor) -> Result<Tensor> {
    let p = check("modulate", x, &[scale, shift], &[])?;
    let y = Tensor::empty(x.gpu(), x.shape(), DType::F32)?;
    rec.dispatch_elements(
        ADALN_MODULATE,
        p.n as u64,
        args::AdalnModulateArgs { a: x, p: scale, q: shift, out: &y },
        &p,
    )?;
    Ok(y)
}

/// `out = res + gate * y`.
pub fn gate(rec: &mut Recorder, y: &Tensor, gate: &Tensor, res: &Tensor) -> Result<Tensor> {
    let p = check("gated residual", y, &[gate], &[res])?;
    let out = Tensor::empty(y.gpu(), y.shape(), DType::F32)?;
    rec.dispatch_elements(
        ADALN_GATE,
        p.n as u64,
        args::AdalnGateArgs { a: y, p: gate, q: res, out: &out },
        &p,
    )?;
    Ok(out)
}

/// `(dy * (one + p), dy * a)` for `a [B, T, D]`, per-sample `p [B, D]` and `dy` like `a`.
pub fn backward(
    rec: &mut Recorder,
    a: &Tensor,
    p: &Tensor,
    dy: &Tensor,
    one: f32,
) -> Result<(Tensor, Tensor)> {
    let params = Params { one, ..check("adaln backward", a, &[p], &[dy])? };
    let ga = Tensor::empty(a.gpu(), a.shape(), DType::F32)?;
    let gp = Tensor::empty(a.gpu(), a.shape(), DType::F32)?;
    rec.dispatch_elements(
        ADALN_BACKWARD,
        params.n as u64,
        args::AdalnBackwardArgs { a, p, g: dy, ga: &ga, gp: &gp },
        &params,
    )?;
    Ok((ga, gp))
}

/// Plain f64 loops.
pub mod reference {
    /// `y = x * (1 + scale) + shift`, `x [b, t, d]`, `shift`, `scale [b, d]`.
    pub fn modulate(x: &[f64], shift: &[f64], scale: &[f64], b: usize, t: usize, d: usize) -> Vec<f64> {
        let mut y = vec![0.0; b * t * d];
        for s in 0..b {
            for k in 0..t {
                for j in 0..d {
                    let i = (s * t + k) * d + j;
                    y[i] = x[i] * (1.0 + scale[s * d + j]) + shift[s * d + j];
                }
            }
        }
        y
    }

    /// Returns `(dx, dshift, dscale)`.
    pub fn modulate_backward(
        x: &[f64],
        scale: &[f64],
        dy: &[f64],
        b: usize,
        t: usize,
        d: usize,
    ) -> [Vec<f64>; 3] {
        let (mut dx, mut dshift, mut dscale) = (vec![0.0; b * t * d], vec![0.0; b * d], vec![0.0; b * d]);
        for s in 0..b {
            for k in 0..t {
                for j in 0..d {
                    let i = (s * t + k) * d + j;
                    dx[i] = dy[i] * (1.0 + scale[s * d + j]);
                    dshift[s * d + j] += dy[i];
                    dscale[s * d + j] += dy[i] * x[i];
                }
            }
        }
        [dx, dshift, dscale]
    }

    /// `out = res + gate * y`, `res`, `y [b, t, d]`, `gate [b, d]`.
    pub fn gated_residual(res: &[f64], gate: &[f64], y: &[f64], b: usize, t: usize, d: usize) -> Vec<f64> {
        (0..b * t * d).map(|i| res[i] + gate[(i / (t * d)) * d + i % d] * y[i]).collect()
    }

    /// Returns `(dres, dgate, dy)`.
    pub fn gated_residual_backward(
        gate: &[f64],
        y: &[f64],
        dout: &[f64],
        b: usize,
        t: usize,
        d: usize,
    ) -> [Vec<f64>; 3] {
        let mut dgate = vec![0.0; b * d];
        let mut dy = vec![0.0; b * t * d];
        for i in 0..b * t * d {
            let g = (i / (t * d)) * d + i % d;
            dgate[g] += dout[i] * y[i];
            dy[i] = dout[i] * gate[g];
        }
        [dout.to_vec(), dgate, dy]
    }
}
