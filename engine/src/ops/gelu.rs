//! Backward of the exact GELU (the forward is [`crate::ops::unary::Unary::Gelu`]). Kernel:
//! `shaders/gelu.wgsl`.

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::GELU_BACKWARD;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::fit_u32;
use crate::kernels::params::GeluParams as Params;

/// `dx = dy * gelu'(x)`.
pub fn gelu_backward(rec: &mut Recorder, x: &Tensor, dy: &Tensor) -> Result<Tensor> {
    if x.dtype() != DType::F32 || dy.dtype() != DType::F32 || x.shape() != dy.shape() {
        return Err(Error::Shape(format!("gelu backward: x {x:?} and dy {dy:?} must be f32 of one shape")));
    }
    let n = fit_u32(x.numel(), || format!("gelu backward of {x:?}"))?;
    let dx = Tensor::empty(x.gpu(), x.shape(), DType::F32)?;
    rec.dispatch_linear(
        GELU_BACKWARD,
        (n as u64).div_ceil(256),
        args::GeluBackwardArgs { x, dy, dx: &dx },
        &Params { n },
    )?;
    Ok(dx)
}

/// Plain f64 loops.
pub mod reference {
    use crate::ops::unary::reference::erf;

    /// gelu'(v) = Phi(v) + v phi(v).
    pub fn gelu_grad(v: f64) -> f64 {
        let cdf = 0.5 * (1.0 + erf(v / std::f64::consts::SQRT_2));
        let pdf = (-0.5 * v * v).exp() / (2.0 * std::f64::consts::PI).sqrt();
        cdf + v * pdf
    }

    pub fn gelu_backward(x: &[f64], dy: &[f64]) -> Vec<f64> {
        x.iter().zip(dy).map(|(&v, &g)| g * gelu_grad(v)).collect()
    }
}
