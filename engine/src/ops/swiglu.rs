//! The SwiGLU gate `h = silu(a) * b` and its backward, fused. Kernel: `shaders/swiglu.wgsl`.
//!
//! Tests: the harness's `swiglu` row (`engine/tests/ops/cases.rs`: forward and backward, the
//! reference against finite differences against the f64 reference at awkward shapes); the
//! feed-forward layer's `tests/models/layers.rs`.

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{SWIGLU_BACKWARD, SWIGLU_FORWARD, SWIGLU_SILU_BACKWARD};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::fit_u32;
use crate::kernels::params::SwigluParams as Params;

fn check(what: &str, ts: &[&Tensor]) -> Result<Params> {
    let shape = ts[0].shape();
    if ts.iter().any(|t| t.dtype() != DType::F32 || t.shape() != shape) {
        return Err(Error::Shape(format!("{what}: needs f32 tensors of one shape, got {ts:?}")));
    }
    let n = fit_u32(ts[0].numel(), || format!("{what} of {:?}", ts[0]))?;
    Ok(Params { n })
}

/// `h = silu(a) * b`.
pub fn swiglu(rec: &mut Recorder, a: &Tensor, b: &Tensor) -> Result<Tensor> {
    let p = check("swiglu", &[a, b])?;
    let h = Tensor::empty(a.gpu(), a.shape(), DType::F32)?;
    rec.dispatch_elements(SWIGLU_FORWARD, p.n as u64, args::SwigluForwardArgs { a, b, h: &h }, &p)?;
    Ok(h)
}

/// Returns `(da, db)` from `dh`.
pub fn swiglu_backward(rec: &mut Recorder, a: &Tensor, b: &Tensor, dh: &Tensor) -> Result<(Tensor, Tensor)> {
    let da = Tensor::empty(a.gpu(), a.shape(), DType::F32)?;
    let db = Tensor::empty(a.gpu(), a.shape(), DType::F32)?;
    swiglu_backward_into(rec, a, b, dh, &da, &db)?;
    Ok((da, db))
}

/// [`swiglu_backward`] into given tensors (shaped like `a`; views of one stacked gradient,
/// say).
pub fn swiglu_backward_into(
    rec: &mut Recorder,
    a: &Tensor,
    b: &Tensor,
    dh: &Tensor,
    da: &Tensor,
    db: &Tensor,
) -> Result<()> {
    let p = check("swiglu backward", &[a, b, dh, da, db])?;
    rec.dispatch_elements(SWIGLU_BACKWARD, p.n as u64, args::SwigluBackwardArgs { a, b, dh, da, db }, &p)
}

/// `silu'(a) * dy`, the backward of `silu(a) = a sigmoid(a)` (the gate's `da` with `b = 1`).
pub fn silu_backward(rec: &mut Recorder, a: &Tensor, dy: &Tensor) -> Result<Tensor> {
    let p = check("silu backward", &[a, dy])?;
    let da = Tensor::empty(a.gpu(), a.shape(), DType::F32)?;
    rec.dispatch_elements(
        SWIGLU_SILU_BACKWARD,
        p.n as u64,
        args::SwigluSiluBackwardArgs { a, dh: dy, dsilu: &da },
        &p,
    )?;
    Ok(da)
}

/// Plain f64 loops.
pub mod reference {
    fn sigmoid(v: f64) -> f64 {
        1.0 / (1.0 + (-v).exp())
    }

    pub fn swiglu(a: &[f64], b: &[f64]) -> Vec<f64> {
        a.iter().zip(b).map(|(&a, &b)| a * sigmoid(a) * b).collect()
    }

    /// Returns (da, db).
    pub fn swiglu_backward(a: &[f64], b: &[f64], dh: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let mut da = Vec::with_capacity(a.len());
        let mut db = Vec::with_capacity(a.len());
        for i in 0..a.len() {
            let s = sigmoid(a[i]);
            da.push(dh[i] * b[i] * s * (1.0 + a[i] * (1.0 - s)));
            db.push(dh[i] * a[i] * s);
        }
        (da, db)
    }
}
