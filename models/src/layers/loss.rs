//! Mean losses: each gives the scalar loss as a 1-element tensor and the gradient of its input.
//! Kernel: `shaders/loss.wgsl`; host side `engine/src/ops/loss.rs`.
//!
//! Tests: `tests/models/layers.rs` (every loss against the reference, saturated logits) and the
//! engine's harness row of the losses.

use velox_engine::ops::fill::fill;
pub use velox_engine::ops::loss::LossKind;
use velox_engine::ops::loss::{loss, loss_into};
use velox_engine::{DType, Error, Recorder, Result, Tensor};

/// `weight * mean(loss(pred, target))`.
#[derive(Clone, Copy, Debug)]
pub struct Loss {
    pub kind: LossKind,
    pub weight: f32,
}

impl Loss {
    pub fn mse() -> Loss {
        Loss { kind: LossKind::Mse, weight: 1.0 }
    }
    pub fn l1() -> Loss {
        Loss { kind: LossKind::L1, weight: 1.0 }
    }
    pub fn huber(delta: f32) -> Loss {
        Loss { kind: LossKind::Huber { delta }, weight: 1.0 }
    }
    /// Numerically stable: `max(x, 0) - x y + log(1 + exp(-|x|))`.
    pub fn bce_with_logits() -> Loss {
        Loss { kind: LossKind::BceWithLogits, weight: 1.0 }
    }
    /// The focal loss with logits, focusing `gamma` (at least 1).
    pub fn focal(gamma: f32) -> Loss {
        Loss { kind: LossKind::Focal { gamma }, weight: 1.0 }
    }
    pub fn weighted(self, weight: f32) -> Loss {
        Loss { weight, ..self }
    }

    /// `(loss [1], dloss/dpred)`: the forward and the backward in one pass.
    pub fn forward_backward(
        &self,
        rec: &mut Recorder,
        pred: &Tensor,
        target: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        loss(rec, self.kind, pred, target, self.weight)
    }

    /// `dloss/dpred`, with the loss written into `total` (f32 `[1]`) or added to what it holds
    /// (`accumulate`).
    pub fn forward_backward_into(
        &self,
        rec: &mut Recorder,
        pred: &Tensor,
        target: &Tensor,
        total: &Tensor,
        accumulate: bool,
    ) -> Result<Tensor> {
        loss_into(rec, self.kind, pred, target, self.weight, total, accumulate)
    }

    /// `(loss [1], dloss/dpred)` for `pred` and `target` split into consecutive segments of
    /// `rows` rows each (the first axis): `weight` times the sum over the segments of each
    /// segment's mean. A batch's samples with different numbers of rows each get their own
    /// mean this way.
    pub fn forward_backward_segments(
        &self,
        rec: &mut Recorder,
        pred: &Tensor,
        target: &Tensor,
        rows: &[usize],
    ) -> Result<(Tensor, Tensor)> {
        let total_rows = pred.shape().first().copied().unwrap_or(0);
        if pred.shape() != target.shape() || rows.iter().sum::<usize>() != total_rows {
            return Err(Error::Shape(format!(
                "segment losses: pred {pred:?} and target {target:?} must share a shape whose rows are the segments' {rows:?}"
            )));
        }
        let gpu = pred.gpu().clone();
        let sum = Tensor::empty(&gpu, &[1], DType::F32)?;
        if rows.is_empty() {
            fill(rec, &sum, 0.0)?;
        }
        let grad = Tensor::empty(&gpu, pred.shape(), DType::F32)?;
        let mut at = 0;
        for (i, &count) in rows.iter().enumerate() {
            let slice = |rec: &mut Recorder, t: &Tensor| -> Result<Tensor> {
                let mut shape = t.shape().to_vec();
                shape[0] = count;
                let out = Tensor::empty(&gpu, &shape, t.dtype())?;
                rec.copy_rows(t, at, &out, 0, count)?;
                Ok(out)
            };
            let (p, t) = (slice(rec, pred)?, slice(rec, target)?);
            let g = self.forward_backward_into(rec, &p, &t, &sum, i > 0)?;
            rec.copy_rows(&g, 0, &grad, at, count)?;
            at += count;
        }
        Ok((sum, grad))
    }
}
