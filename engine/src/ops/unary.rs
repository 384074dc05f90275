//! Elementwise maps over f32. Kernel: `shaders/unary.wgsl`.

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::UNARY_MAIN;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// The maps; the discriminants are the op codes in `shaders/unary.wgsl`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Unary {
    /// alpha * x + beta
    Affine(f32, f32),
    Exp,
    Log,
    Sigmoid,
    Silu,
    /// Exact GELU, 0.5 x (1 + erf(x / sqrt 2)).
    Gelu,
    /// The tanh approximation of GELU.
    GeluTanh,
    Sqrt,
    Rsqrt,
    Abs,
    Tanh,
    Relu,
    Square,
    Recip,
    Sin,
    Cos,
}

impl Unary {
    pub const ALL: [Unary; 16] = [
        Unary::Affine(1.5, -0.25),
        Unary::Exp,
        Unary::Log,
        Unary::Sigmoid,
        Unary::Silu,
        Unary::Gelu,
        Unary::GeluTanh,
        Unary::Sqrt,
        Unary::Rsqrt,
        Unary::Abs,
        Unary::Tanh,
        Unary::Relu,
        Unary::Square,
        Unary::Recip,
        Unary::Sin,
        Unary::Cos,
    ];

    fn code(self) -> (u32, f32, f32) {
        match self {
            Unary::Affine(a, b) => (0, a, b),
            Unary::Exp => (1, 0.0, 0.0),
            Unary::Log => (2, 0.0, 0.0),
            Unary::Sigmoid => (3, 0.0, 0.0),
            Unary::Silu => (4, 0.0, 0.0),
            Unary::Gelu => (5, 0.0, 0.0),
            Unary::GeluTanh => (6, 0.0, 0.0),
            Unary::Sqrt => (7, 0.0, 0.0),
            Unary::Rsqrt => (8, 0.0, 0.0),
            Unary::Abs => (9, 0.0, 0.0),
            Unary::Tanh => (10, 0.0, 0.0),
            Unary::Relu => (11, 0.0, 0.0),
            Unary::Square => (12, 0.0, 0.0),
            Unary::Recip => (13, 0.0, 0.0),
            Unary::Sin => (14, 0.0, 0.0),
            Unary::Cos => (15, 0.0, 0.0),
        }
    }
}

use crate::kernels::params::UnaryParams as Params;

/// y = f(x) as a new tensor.
pub fn unary(rec: &mut Recorder, x: &Tensor, f: Unary) -> Result<Tensor> {
    let y = Tensor::empty(x.gpu(), x.shape(), DType::F32)?;
    unary_into(rec, x, &y, f)?;
    Ok(y)
}

/// y = f(x) into `y` (which may be `x` itself).
pub fn unary_into(rec: &mut Recorder, x: &Tensor, y: &Tensor, f: Unary) -> Result<()> {
    if x.dtype() != DType::F32 || y.dtype() != DType::F32 || x.numel() != y.numel() {
        return Err(Error::Shape(format!("unary {f:?}: {x:?} -> {y:?} needs f32 tensors of equal size")));
    }
    let n = fit_u32(x.numel(), || format!("unary on {x:?}"))?;
    let (op, alpha, beta) = f.code();
    rec.dispatch_linear(
        UNARY_MAIN,
        (n as u64).div_ceil(256),
        args::UnaryMainArgs { x, y },
        &Params { n, op, alpha, beta },
    )
}

pub mod reference {
    use super::Unary;

    /// erf by its Maclaurin series near 0 and its continued fraction beyond (f64 accurate).
    pub fn erf(x: f64) -> f64 {
        let ax = x.abs();
        let r = if ax < 2.5 {
            // sum_n (-1)^n x^(2n+1) / (n! (2n+1)), 2/sqrt(pi)
            let mut term = ax;
            let mut sum = ax;
            let mut n = 0.0;
            while term.abs() > 1e-17 * sum.abs() {
                n += 1.0;
                term *= -ax * ax / n;
                sum += term / (2.0 * n + 1.0);
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        } else {
            // erfc(x) = exp(-x^2)/sqrt(pi) * 1/(x + 1/2/(x + 1/(x + 3/2/(x + ...))))
            let mut f = ax;
            for k in (1..60).rev() {
                f = ax + (k as f64 / 2.0) / f;
            }
            1.0 - (-ax * ax).exp() / (std::f64::consts::PI.sqrt() * f)
        };
        r.copysign(x)
    }

    pub fn apply(f: Unary, v: f64) -> f64 {
        let sigmoid = |v: f64| 1.0 / (1.0 + (-v).exp());
        match f {
            Unary::Affine(a, b) => a as f64 * v + b as f64,
            Unary::Exp => v.exp(),
            Unary::Log => v.ln(),
            Unary::Sigmoid => sigmoid(v),
            Unary::Silu => v * sigmoid(v),
            Unary::Gelu => 0.5 * v * (1.0 + erf(v / std::f64::consts::SQRT_2)),
            Unary::GeluTanh => {
                0.5 * v * (1.0 + (0.797_884_560_802_865_4 * (v + 0.044715 * v * v * v)).tanh())
            }
            Unary::Sqrt => v.sqrt(),
            Unary::Rsqrt => 1.0 / v.sqrt(),
            Unary::Abs => v.abs(),
            Unary::Tanh => v.tanh(),
            Unary::Relu => v.max(0.0),
            Unary::Square => v * v,
            Unary::Recip => 1.0 / v,
            Unary::Sin => v.sin(),
            Unary::Cos => v.cos(),
        }
    }

    pub fn unary(x: &[f32], f: Unary) -> Vec<f64> {
        x.iter().map(|&v| apply(f, v as f64)).collect()
    }
}
