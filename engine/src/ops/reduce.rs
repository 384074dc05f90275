//! Sum, mean and max along one axis. Kernel: `shaders/reduce.wgsl`.
//!
//! Tests: the harness's `reduce` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/elementwise.rs` (empty axes, bad shapes).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::{REDUCE_ROWS, REDUCE_STRIDED};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// The reductions, each one of the op codes `REDUCE_OP_*` of `shaders/reduce.wgsl` (exported
/// by the build; checked both ways by the harness).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reduce {
    Sum,
    Mean,
    Max,
}

impl Reduce {
    pub const ALL: &[Reduce] = &[Reduce::Sum, Reduce::Mean, Reduce::Max];

    /// The shader's op code.
    pub fn code(self) -> u32 {
        use crate::kernels as k;
        match self {
            Reduce::Sum => k::REDUCE_OP_SUM,
            Reduce::Mean => k::REDUCE_OP_MEAN,
            Reduce::Max => k::REDUCE_OP_MAX,
        }
    }
}

use crate::kernels::params::ReduceParams as Params;

/// Reduces `x` along `axis`, which is removed from the shape. The sum and mean of an empty
/// axis are 0; the max of an empty axis is an error.
pub fn reduce(rec: &mut Recorder, x: &Tensor, axis: usize, op: Reduce) -> Result<Tensor> {
    let mut out_shape = x.shape().to_vec();
    if axis < out_shape.len() {
        out_shape.remove(axis);
    }
    let out = Tensor::empty(x.gpu(), &out_shape, DType::F32)?;
    reduce_into(rec, x, axis, op, &out, false)?;
    Ok(out)
}

/// [`reduce`] into `out` (f32, the reduced shape or any shape of as many elements), or added
/// to what `out` holds when `accumulate` (a bias gradient into its parameter's gradient).
pub fn reduce_into(
    rec: &mut Recorder,
    x: &Tensor,
    axis: usize,
    op: Reduce,
    out: &Tensor,
    accumulate: bool,
) -> Result<()> {
    let shape = x.shape();
    if x.dtype() != DType::F32 {
        return Err(Error::Shape(format!("reduce {op:?} needs f32, got {x:?}")));
    }
    if axis >= shape.len() {
        return Err(Error::Shape(format!("reduce {op:?}: axis {axis} out of range for {x:?}")));
    }
    let outer: usize = shape[..axis].iter().product();
    let len = shape[axis];
    let inner: usize = shape[axis + 1..].iter().product();
    if len == 0 && op == Reduce::Max {
        return Err(Error::Shape(format!("max over an empty axis of {x:?}")));
    }
    if out.dtype() != DType::F32 || out.numel() != outer * inner {
        return Err(Error::Shape(format!(
            "reduce {op:?} of {x:?} along axis {axis}: out must be f32 with {} values, got {out:?}",
            outer * inner
        )));
    }
    if out.same_storage(x) {
        return Err(Error::Shape(format!("reduce {op:?}: out shares storage with the input")));
    }
    let fit = |v: usize| fit_u32(v, || format!("reduce of {x:?}"));
    let p = Params {
        outer: fit(outer)?,
        len: fit(len)?,
        inner: fit(inner)?,
        op: op.code(),
        accumulate: accumulate as u32,
    };
    fit(x.numel())?;
    if inner == 1 {
        rec.dispatch_linear(REDUCE_ROWS, outer as u64, args::ReduceRowsArgs { x, y: out }, &p)?;
    } else {
        rec.dispatch_linear(
            REDUCE_STRIDED,
            ((outer * inner) as u64).div_ceil(256),
            args::ReduceStridedArgs { x, y: out },
            &p,
        )?;
    }
    Ok(())
}

pub mod reference {
    use super::Reduce;

    pub fn reduce(x: &[f32], shape: &[usize], axis: usize, op: Reduce) -> Vec<f64> {
        let outer: usize = shape[..axis].iter().product();
        let len = shape[axis];
        let inner: usize = shape[axis + 1..].iter().product();
        let mut out = Vec::with_capacity(outer * inner);
        for a in 0..outer {
            for c in 0..inner {
                let vals = (0..len).map(|j| x[(a * len + j) * inner + c] as f64);
                out.push(match op {
                    Reduce::Sum => vals.sum(),
                    Reduce::Mean => vals.sum::<f64>() / len.max(1) as f64,
                    Reduce::Max => vals.fold(f64::NEG_INFINITY, f64::max),
                });
            }
        }
        out
    }
}
