//! Mean losses with their gradients: MSE, L1, Huber, binary cross-entropy with logits and
//! the focal loss with logits.
//! Kernel: `shaders/loss.wgsl` (per-element loss and gradient), then a sum by `reduce.wgsl`.
//!
//! Tests: the harness's `loss` row (`engine/tests/ops/cases.rs`: forward and its gradient, the
//! reference against finite differences against the f64 reference at awkward shapes);
//! `tests/models/layers.rs` (saturated logits, the focal loss's range).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::LOSS_MAIN;
use crate::ops::reduce::{reduce_into, Reduce};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// The losses; the discriminants are the codes in `shaders/loss.wgsl`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LossKind {
    /// (p - t)^2
    Mse,
    /// |p - t|
    L1,
    /// 0.5 r^2 for |r| <= delta, delta (|r| - delta / 2) beyond.
    Huber { delta: f32 },
    /// Binary cross-entropy of logits p against labels t in [0, 1].
    BceWithLogits,
    /// The focal loss (Lin et al. 2017) of logits against labels in [0, 1]: the BCE times
    /// `q^gamma`, q the probability given to the wrong answer, so confident right answers
    /// (most voxels of a sparse grid) weigh little. `gamma` at least 1 (0 is BCE).
    Focal { gamma: f32 },
}

impl LossKind {
    /// The shader's op code (`LOSS_OP_*` of `shaders/loss.wgsl`) and the kind's parameter.
    pub fn code(self) -> (u32, f32) {
        use crate::kernels as k;
        match self {
            LossKind::Mse => (k::LOSS_OP_MSE, 0.0),
            LossKind::L1 => (k::LOSS_OP_L1, 0.0),
            LossKind::Huber { delta } => (k::LOSS_OP_HUBER, delta),
            LossKind::BceWithLogits => (k::LOSS_OP_BCE, 0.0),
            LossKind::Focal { gamma } => (k::LOSS_OP_FOCAL, gamma),
        }
    }
}

use crate::kernels::params::LossParams as Params;

/// `weight * mean(loss(pred, target))` as a 1-element tensor, and its gradient with respect to
/// `pred`. An empty input has loss 0.
pub fn loss(
    rec: &mut Recorder,
    kind: LossKind,
    pred: &Tensor,
    target: &Tensor,
    weight: f32,
) -> Result<(Tensor, Tensor)> {
    let total = Tensor::empty(pred.gpu(), &[1], DType::F32)?;
    let grad = loss_into(rec, kind, pred, target, weight, &total, false)?;
    Ok((total, grad))
}

/// [`loss`] with the loss written into `total` (f32 `[1]`), or added to it (`accumulate`: a
/// sum of losses over views or segments without an add of its own); returns the gradient.
pub fn loss_into(
    rec: &mut Recorder,
    kind: LossKind,
    pred: &Tensor,
    target: &Tensor,
    weight: f32,
    total: &Tensor,
    accumulate: bool,
) -> Result<Tensor> {
    if pred.dtype() != DType::F32 || target.dtype() != DType::F32 || pred.shape() != target.shape() {
        return Err(Error::Shape(format!(
            "{kind:?} loss: pred {pred:?} and target {target:?} must be f32 of one shape"
        )));
    }
    if let LossKind::Focal { gamma } = kind {
        if !(gamma.is_finite() && (1.0..=16.0).contains(&gamma)) {
            return Err(Error::Invalid(format!("focal loss: gamma {gamma} must be in [1, 16]")));
        }
    }
    let n = fit_u32(pred.numel(), || format!("{kind:?} loss of {pred:?}"))?;
    let (code, delta) = kind.code();
    let p = Params { n, kind: code, delta, scale: weight / n.max(1) as f32 };
    let per = Tensor::empty(pred.gpu(), &[n as usize], DType::F32)?;
    let grad = Tensor::empty(pred.gpu(), pred.shape(), DType::F32)?;
    rec.dispatch_elements(
        LOSS_MAIN,
        n as u64,
        args::LossMainArgs { pred, label: target, loss: &per, grad: &grad },
        &p,
    )?;
    reduce_into(rec, &per, 0, Reduce::Sum, total, accumulate)?;
    Ok(grad)
}

/// Plain f64 loops.
pub mod reference {
    use super::LossKind;

    /// Per-element (loss, d loss / d pred).
    pub fn pointwise(kind: LossKind, p: f64, t: f64) -> (f64, f64) {
        let r = p - t;
        match kind {
            LossKind::Mse => (r * r, 2.0 * r),
            LossKind::L1 => (r.abs(), if r == 0.0 { 0.0 } else { r.signum() }),
            LossKind::Huber { delta } => {
                let d = delta as f64;
                if r.abs() <= d {
                    (0.5 * r * r, r)
                } else {
                    (d * (r.abs() - 0.5 * d), d * r.signum())
                }
            }
            LossKind::BceWithLogits => {
                let l = p.max(0.0) - p * t + (-p.abs()).exp().ln_1p();
                (l, 1.0 / (1.0 + (-p).exp()) - t)
            }
            LossKind::Focal { gamma } => {
                let g = gamma as f64;
                let ce = p.max(0.0) - p * t + (-p.abs()).exp().ln_1p();
                let s = 1.0 / (1.0 + (-p).exp());
                let q = t / (1.0 + p.exp()) + (1.0 - t) * s;
                let qg = q.powf(g);
                let focus = if q > 0.0 { g * qg / q * (1.0 - 2.0 * t) * s * (1.0 - s) * ce } else { 0.0 };
                (qg * ce, qg * (s - t) + focus)
            }
        }
    }

    /// `weight * mean(loss)` and its gradient.
    pub fn loss(kind: LossKind, pred: &[f64], target: &[f64], weight: f64) -> (f64, Vec<f64>) {
        let scale = weight / pred.len().max(1) as f64;
        let mut total = 0.0;
        let mut grad = Vec::with_capacity(pred.len());
        for (&p, &t) in pred.iter().zip(target) {
            let (l, g) = pointwise(kind, p, t);
            total += l * scale;
            grad.push(g * scale);
        }
        (total, grad)
    }
}
