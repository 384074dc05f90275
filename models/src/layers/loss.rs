//! Mean losses: each gives the scalar loss as a 1-element tensor and the gradient of its input.
//! Kernel: `shaders/loss.wgsl`; host side `engine/src/ops/loss.rs`.

use velox_engine::ops::loss::loss;
pub use velox_engine::ops::loss::LossKind;
use velox_engine::{Recorder, Result, Tensor};

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
}
