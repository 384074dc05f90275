//! Backward of the exact GELU (the forward is [`crate::ops::unary::Unary::Gelu`]): the unary
//! backward of `shaders/unary.wgsl` for it. Tests: the harness's unary rows
//! (`engine/tests/ops/cases.rs`).

use crate::error::Result;
use crate::ops::unary::{unary_backward, Unary};
use crate::recorder::Recorder;
use crate::tensor::Tensor;

/// `dx = dy * gelu'(x)`.
pub fn gelu_backward(rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor> {
    unary_backward(rec, x, dy, Unary::Gelu)
}

/// Plain f64 loops.
pub mod reference {
    use crate::ops::unary::{reference::derivative, Unary};

    /// gelu'(v) = Phi(v) + v phi(v).
    pub fn gelu_grad(v: f64) -> f64 {
        derivative(Unary::Gelu, v)
    }

    pub fn gelu_backward(x: &[f64], dy: &[f64]) -> Vec<f64> {
        x.iter().zip(dy).map(|(&v, &g)| g * gelu_grad(v)).collect()
    }
}
