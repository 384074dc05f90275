//! Softmax over the last axis. Kernel: `shaders/softmax.wgsl`.
//!
//! Tests: the harness's `softmax` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/elementwise.rs` (stability on long and extreme
//! rows).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::SOFTMAX_MAIN;
use crate::ops::rmsnorm::{row_groups, row_lanes};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::fit_u32;
use crate::kernels::params::SoftmaxParams as Params;

/// Softmax of every row (last axis) of `x`, as a new tensor.
pub fn softmax(rec: &mut Recorder, x: &Tensor) -> Result<Tensor> {
    if x.dtype() != DType::F32 || x.shape().is_empty() {
        return Err(Error::Shape(format!("softmax needs an f32 tensor with at least one axis, got {x:?}")));
    }
    let len = *x.shape().last().unwrap();
    let rows = x.numel().checked_div(len).unwrap_or(0);
    let out = Tensor::empty(x.gpu(), x.shape(), DType::F32)?;
    let fit = |v: usize| fit_u32(v, || format!("softmax of {x:?}"));
    fit(x.numel())?;
    let (rows, len) = (fit(rows)?, fit(len)?);
    let lanes = row_lanes(len);
    rec.dispatch_linear(
        SOFTMAX_MAIN,
        row_groups(rows, lanes),
        args::SoftmaxMainArgs { x, y: &out },
        &Params { rows, len, lanes },
    )?;
    Ok(out)
}

pub mod reference {
    /// Row softmax in f64 with the maximum subtracted.
    pub fn softmax(x: &[f32], len: usize) -> Vec<f64> {
        let mut out = Vec::with_capacity(x.len());
        for row in x.chunks(len.max(1)) {
            let m = row.iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v as f64));
            let s: f64 = row.iter().map(|&v| (v as f64 - m).exp()).sum();
            out.extend(row.iter().map(|&v| (v as f64 - m).exp() / s));
        }
        out
    }
}
