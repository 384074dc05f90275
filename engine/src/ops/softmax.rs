//! Softmax over the last axis. Kernels: `shaders/softmax.wgsl` (rows of any length; its
//! workgroup of 256 for GPUs, of 8 with a row per invocation for CPU devices) and
//! `shaders/softmax_cpu.wgsl` (CPU devices, rows of a multiple of 4, read as vec4s through a
//! texel buffer).
//!
//! Tests: the harness's `softmax` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/elementwise.rs` (stability on long and extreme
//! rows).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{SOFTMAX_CPU_MAIN, SOFTMAX_WG256_MAIN, SOFTMAX_WG8_MAIN};
use crate::ops::rmsnorm::RowShape;
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
    let shape = RowShape::of(x.gpu(), len);
    if shape.cpu && len.is_multiple_of(4) && x.texel_bindable() {
        // Rows of vec4s read through a texel buffer (`shaders/softmax_cpu.wgsl`).
        let p = crate::kernels::params::SoftmaxCpuParams { rows, len, lanes: 1 };
        return rec
            .dispatch_linear(
                SOFTMAX_CPU_MAIN,
                shape.groups(rows),
                args::SoftmaxCpuMainArgs { x, y: &out },
                &p,
            )
            .map(|_| out);
    }
    rec.dispatch_linear(
        shape.pick(SOFTMAX_WG256_MAIN, SOFTMAX_WG8_MAIN),
        shape.groups(rows),
        args::SoftmaxWg256MainArgs { x, y: &out },
        &Params { rows, len, lanes: shape.lanes },
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
