//! RMSNorm and LayerNorm over the last axis. Kernels: `shaders/rmsnorm.wgsl`,
//! `shaders/layernorm.wgsl` (host sides in `engine/src/ops/{rmsnorm,layernorm}.rs`).
//!
//! Tests: `tests/models/layers.rs` (against the reference, residual gradients, stability).

use velox_engine::ops::layernorm::{layernorm, layernorm_backward};
use velox_engine::ops::rmsnorm::{rmsnorm, rmsnorm_backward};
use velox_engine::{Error, Recorder, Result, Tensor};

use super::{expect_shape, Param};

/// `y = x / sqrt(mean(x^2) + eps) * w`.
pub struct RmsNorm {
    /// `[width]`
    pub weight: Param,
    pub eps: f32,
}

#[derive(Clone, Debug)]
pub struct RmsNormCache {
    x: Tensor,
    rstd: Tensor,
}

impl RmsNorm {
    pub fn new(weight: Param, eps: f32) -> Result<RmsNorm> {
        if weight.shape().len() != 1 {
            return Err(Error::Shape(format!("rmsnorm weight must be [width], got {:?}", weight.shape())));
        }
        Ok(RmsNorm { weight, eps })
    }

    pub fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, RmsNormCache)> {
        let (y, rstd) = rmsnorm(rec, x, &self.weight.value, self.eps)?;
        Ok((y, RmsNormCache { x: x.clone(), rstd }))
    }

    /// Adds `dw` into the weight's gradient and returns `dx`.
    pub fn backward(&self, rec: &mut Recorder, cache: &RmsNormCache, dy: &Tensor) -> Result<Tensor> {
        self.backward_plus(rec, cache, dy, None)
    }

    /// [`RmsNorm::backward`] with `residual` added into `dx` in the same pass: the input
    /// gradient of a pre-norm residual block `x + f(norm(x))`, `residual` being its output's.
    pub fn backward_plus(
        &self,
        rec: &mut Recorder,
        cache: &RmsNormCache,
        dy: &Tensor,
        residual: Option<&Tensor>,
    ) -> Result<Tensor> {
        let (w, dw) = (&self.weight.value, Some(&self.weight.grad));
        rmsnorm_backward(rec, &cache.x, w, &cache.rstd, dy, dw, residual)
    }
}

/// `y = (x - mean) / sqrt(var + eps) (* w + b)`.
pub struct LayerNorm {
    /// `(w, b)`, each `[width]`, or none for a plain normalisation (as under adaLN).
    pub affine: Option<(Param, Param)>,
    pub width: usize,
    pub eps: f32,
}

#[derive(Clone, Debug)]
pub struct LayerNormCache {
    x: Tensor,
    mean: Tensor,
    rstd: Tensor,
}

impl LayerNorm {
    pub fn new(width: usize, affine: Option<(Param, Param)>, eps: f32) -> Result<LayerNorm> {
        if let Some((w, b)) = &affine {
            expect_shape("layernorm weight", w, &[width])?;
            expect_shape("layernorm bias", b, &[width])?;
        }
        Ok(LayerNorm { affine, width, eps })
    }

    pub fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, LayerNormCache)> {
        let affine = self.affine.as_ref().map(|(w, b)| (&w.value, &b.value));
        let out = layernorm(rec, x, self.width, affine, self.eps)?;
        Ok((out.y, LayerNormCache { x: x.clone(), mean: out.mean, rstd: out.rstd }))
    }

    /// Adds `dw`, `db` into the gradients (with affine) and returns `dx`.
    pub fn backward(&self, rec: &mut Recorder, cache: &LayerNormCache, dy: &Tensor) -> Result<Tensor> {
        self.backward_plus(rec, cache, dy, None)
    }

    /// [`LayerNorm::backward`] with `residual` added into `dx` in the same pass.
    pub fn backward_plus(
        &self,
        rec: &mut Recorder,
        cache: &LayerNormCache,
        dy: &Tensor,
        residual: Option<&Tensor>,
    ) -> Result<Tensor> {
        let affine = self.affine.as_ref().map(|(w, b)| (&w.value, &w.grad, &b.grad));
        layernorm_backward(rec, &cache.x, self.width, affine, &cache.mean, &cache.rstd, dy, residual)
    }
}
