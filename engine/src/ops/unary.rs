//! Elementwise maps over f32 and their backward. Kernel: `shaders/unary.wgsl`. Tests: the
//! harness (`engine/tests/ops/cases.rs`, forward, backward and the reference against finite
//! differences) and `engine/tests/ops/elementwise.rs` (extremes and stability).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::{UNARY_BACKWARD, UNARY_MAIN};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// The maps, each one of the op codes `UNARY_OP_*` of `shaders/unary.wgsl` (exported by the
/// build; `cases::every_op_code_of_a_shader_has_its_variant` checks that every code has one
/// variant here and every variant a code). An op is added in three places: the shader (its code
/// and its line in `apply`, and its derivative in `derivative`), here (the variant, its code,
/// its f64 value and derivative in [`reference`]) and, if its inputs need a domain, one line of
/// the harness's `unary_input`.
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
    /// Every map (the affine one with one pair of coefficients).
    pub const ALL: &[Unary] = &[
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

    /// The shader's op code, and the affine map's coefficients.
    pub fn code(self) -> (u32, f32, f32) {
        use crate::kernels as k;
        match self {
            Unary::Affine(a, b) => (k::UNARY_OP_AFFINE, a, b),
            Unary::Exp => (k::UNARY_OP_EXP, 0.0, 0.0),
            Unary::Log => (k::UNARY_OP_LOG, 0.0, 0.0),
            Unary::Sigmoid => (k::UNARY_OP_SIGMOID, 0.0, 0.0),
            Unary::Silu => (k::UNARY_OP_SILU, 0.0, 0.0),
            Unary::Gelu => (k::UNARY_OP_GELU, 0.0, 0.0),
            Unary::GeluTanh => (k::UNARY_OP_GELU_TANH, 0.0, 0.0),
            Unary::Sqrt => (k::UNARY_OP_SQRT, 0.0, 0.0),
            Unary::Rsqrt => (k::UNARY_OP_RSQRT, 0.0, 0.0),
            Unary::Abs => (k::UNARY_OP_ABS, 0.0, 0.0),
            Unary::Tanh => (k::UNARY_OP_TANH, 0.0, 0.0),
            Unary::Relu => (k::UNARY_OP_RELU, 0.0, 0.0),
            Unary::Square => (k::UNARY_OP_SQUARE, 0.0, 0.0),
            Unary::Recip => (k::UNARY_OP_RECIP, 0.0, 0.0),
            Unary::Sin => (k::UNARY_OP_SIN, 0.0, 0.0),
            Unary::Cos => (k::UNARY_OP_COS, 0.0, 0.0),
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
    rec.dispatch_elements(UNARY_MAIN, n as u64, args::UnaryMainArgs { x, y }, &Params { n, op, alpha, beta })
}

/// `dx = dy * f'(x)`, a new tensor.
pub fn unary_backward(rec: &mut Recorder, x: &Tensor, dy: &Tensor, f: Unary) -> Result<Tensor> {
    if x.dtype() != DType::F32 || dy.dtype() != DType::F32 || x.shape() != dy.shape() {
        return Err(Error::Shape(format!(
            "unary {f:?} backward: x {x:?} and dy {dy:?} must be f32 of one shape"
        )));
    }
    let n = fit_u32(x.numel(), || format!("unary {f:?} backward of {x:?}"))?;
    let dx = Tensor::empty(x.gpu(), x.shape(), DType::F32)?;
    let (op, alpha, beta) = f.code();
    rec.dispatch_elements(
        UNARY_BACKWARD,
        n as u64,
        args::UnaryBackwardArgs { x, dy, dx: &dx },
        &Params { n, op, alpha, beta },
    )?;
    Ok(dx)
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

    /// f'(v).
    pub fn derivative(f: Unary, v: f64) -> f64 {
        let sigmoid = |v: f64| 1.0 / (1.0 + (-v).exp());
        match f {
            Unary::Affine(a, _) => a as f64,
            Unary::Exp => v.exp(),
            Unary::Log => 1.0 / v,
            Unary::Sigmoid => sigmoid(v) * (1.0 - sigmoid(v)),
            Unary::Silu => sigmoid(v) * (1.0 + v * (1.0 - sigmoid(v))),
            Unary::Gelu => {
                let cdf = 0.5 * (1.0 + erf(v / std::f64::consts::SQRT_2));
                cdf + v * (-0.5 * v * v).exp() / (2.0 * std::f64::consts::PI).sqrt()
            }
            Unary::GeluTanh => {
                let c = 0.797_884_560_802_865_4;
                let t = (c * (v + 0.044715 * v * v * v)).tanh();
                0.5 * (1.0 + t) + 0.5 * v * (1.0 - t * t) * c * (1.0 + 3.0 * 0.044715 * v * v)
            }
            Unary::Sqrt => 0.5 / v.sqrt(),
            Unary::Rsqrt => -0.5 * v.powf(-1.5),
            Unary::Abs => {
                if v == 0.0 {
                    0.0
                } else {
                    v.signum()
                }
            }
            Unary::Tanh => 1.0 - v.tanh() * v.tanh(),
            Unary::Relu => f64::from(u8::from(v > 0.0)),
            Unary::Square => 2.0 * v,
            Unary::Recip => -1.0 / (v * v),
            Unary::Sin => v.cos(),
            Unary::Cos => -v.sin(),
        }
    }

    pub fn unary(x: &[f32], f: Unary) -> Vec<f64> {
        x.iter().map(|&v| apply(f, v as f64)).collect()
    }

    /// `dy * f'(x)`.
    pub fn unary_backward(x: &[f64], dy: &[f64], f: Unary) -> Vec<f64> {
        x.iter().zip(dy).map(|(&v, &g)| g * derivative(f, v)).collect()
    }
}
