//! Feed-forward blocks. Matmuls through [`Linear`], the elementwise parts as fused kernels.
//!
//! - [`SwiGlu`]: `y = W2 (silu(x W1) * (x W3))`, no biases (`shaders/swiglu.wgsl`).
//! - [`GeluMlp`]: `y = W2 gelu(x W1 + b1) + b2`, exact GELU (`shaders/unary.wgsl` forward,
//!   `shaders/gelu.wgsl` backward).
//!
//! Tests: `tests/models/layers.rs` (both feed-forwards against the reference and finite
//! differences).

use velox_engine::ops::gelu::gelu_backward;
use velox_engine::ops::swiglu::{swiglu, swiglu_backward, swiglu_backward_into};
use velox_engine::ops::unary::{unary, Unary};
use velox_engine::{Error, Recorder, Result, Tensor};

use super::linear::{Linear, LinearCache, LinearStack};
use super::Param;
use crate::params::Params;

pub struct SwiGlu {
    /// `[d, hidden]`, the gated branch.
    pub w1: Linear,
    /// `[d, hidden]`, the linear branch.
    pub w3: Linear,
    /// `[hidden, d_out]`
    pub w2: Linear,
    /// W1 and W3 as one stack, where a store holds them one after another
    /// ([`SwiGlu::with_stack`]): one product for both branches.
    w13: Option<LinearStack>,
}

#[derive(Clone, Debug)]
pub struct SwiGluCache {
    x: LinearCache,
    /// `x W1`, `x W3` (views of one `[2, rows, hidden]` tensor when stacked).
    a: Tensor,
    b: Tensor,
    stacked: bool,
    h: LinearCache,
}

impl SwiGlu {
    pub fn new(w1: Param, w3: Param, w2: Param) -> Result<SwiGlu> {
        let (w1, w3, w2) = (Linear::new(w1, None)?, Linear::new(w3, None)?, Linear::new(w2, None)?);
        if w1.in_features != w3.in_features
            || w1.out_features != w3.out_features
            || w2.in_features != w1.out_features
        {
            return Err(Error::Shape(format!(
                "swiglu: W1 [{}, {}], W3 [{}, {}] and W2 [{}, {}] do not chain",
                w1.in_features,
                w1.out_features,
                w3.in_features,
                w3.out_features,
                w2.in_features,
                w2.out_features
            )));
        }
        Ok(SwiGlu { w1, w3, w2, w13: None })
    }

    /// Stacks W1 and W3 (the parameters called `names`) when the store holds them one after
    /// another.
    pub fn with_stack(mut self, params: &Params, names: [&str; 2]) -> Result<SwiGlu> {
        self.w13 = params.stacked(&names)?.map(|w| LinearStack::new(w, None)).transpose()?;
        Ok(self)
    }

    pub fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, SwiGluCache)> {
        self.forward_with(rec, x, None)
    }

    /// `residual + SwiGLU(x)`, the residual added by the last product.
    pub fn forward_plus(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        residual: &Tensor,
    ) -> Result<(Tensor, SwiGluCache)> {
        self.forward_with(rec, x, Some(residual))
    }

    fn forward_with(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        residual: Option<&Tensor>,
    ) -> Result<(Tensor, SwiGluCache)> {
        let (a, b, cx, stacked) = match self.w13.as_ref().filter(|s| s.fits(x, rec.precision())) {
            Some(s) => {
                let (ab, cx) = s.forward(rec, x)?;
                let [a, b]: [Tensor; 2] = s.parts(&ab)?.try_into().expect("two layers");
                (a, b, cx, true)
            }
            None => {
                let (a, cx) = self.w1.forward(rec, x)?;
                let (b, _) = self.w3.forward(rec, x)?;
                (a, b, cx, false)
            }
        };
        let h = swiglu(rec, &a, &b)?;
        let (y, ch) = match residual {
            Some(r) => self.w2.forward_plus(rec, &h, r)?,
            None => self.w2.forward(rec, &h)?,
        };
        Ok((y, SwiGluCache { x: cx, a, b, stacked, h: ch }))
    }

    /// Adds `dW1`, `dW3`, `dW2` into the gradients and returns `dx = da W1^T + db W3^T`.
    pub fn backward(&self, rec: &mut Recorder, cache: &SwiGluCache, dy: &Tensor) -> Result<Tensor> {
        let dh = self.w2.backward(rec, &cache.h, dy)?;
        match self.w13.as_ref().filter(|_| cache.stacked) {
            Some(s) => {
                let (rows, hidden) = (cache.a.shape()[0], self.w1.out_features);
                let dab = Tensor::empty(dy.gpu(), &[2, rows, hidden], velox_engine::DType::F32)?;
                let [da, db]: [Tensor; 2] = s.parts(&dab)?.try_into().expect("two layers");
                swiglu_backward_into(rec, &cache.a, &cache.b, &dh, &da, &db)?;
                let dx = Tensor::empty(dy.gpu(), &[rows, self.w1.in_features], velox_engine::DType::F32)?;
                s.grads_into(rec, &cache.x, &dab, Some((&dx, false)))?;
                let mut shape = dy.shape().to_vec();
                *shape.last_mut().expect("rows of features") = self.w1.in_features;
                dx.reshape(&shape)
            }
            None => {
                let (da, db) = swiglu_backward(rec, &cache.a, &cache.b, &dh)?;
                let dx = self.w1.backward(rec, &cache.x, &da)?;
                self.w3.grads_into(rec, &cache.x, &db, &dx, true)?;
                Ok(dx)
            }
        }
    }
}

pub struct GeluMlp {
    /// `[d, hidden]` with bias.
    pub fc1: Linear,
    /// `[hidden, d_out]` with bias.
    pub fc2: Linear,
}

#[derive(Clone, Debug)]
pub struct GeluMlpCache {
    x: LinearCache,
    /// The pre-activation `x W1 + b1`.
    u: Tensor,
    g: LinearCache,
}

impl GeluMlp {
    pub fn new(w1: Param, b1: Param, w2: Param, b2: Param) -> Result<GeluMlp> {
        GeluMlp::from_linears(Linear::new(w1, Some(b1))?, Linear::new(w2, Some(b2))?)
    }

    /// The MLP of two linear layers with biases, `fc2` reading `fc1`'s output.
    pub fn from_linears(fc1: Linear, fc2: Linear) -> Result<GeluMlp> {
        if fc1.bias.is_none() || fc2.bias.is_none() {
            return Err(Error::Shape("gelu mlp: both linear layers need a bias".into()));
        }
        if fc2.in_features != fc1.out_features {
            return Err(Error::Shape(format!(
                "gelu mlp: W1 [{}, {}] and W2 [{}, {}] do not chain",
                fc1.in_features, fc1.out_features, fc2.in_features, fc2.out_features
            )));
        }
        Ok(GeluMlp { fc1, fc2 })
    }

    pub fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, GeluMlpCache)> {
        let (u, cx) = self.fc1.forward(rec, x)?;
        let g = unary(rec, &u, Unary::Gelu)?;
        let (y, cg) = self.fc2.forward(rec, &g)?;
        Ok((y, GeluMlpCache { x: cx, u, g: cg }))
    }

    pub fn backward(&self, rec: &mut Recorder, cache: &GeluMlpCache, dy: &Tensor) -> Result<Tensor> {
        let dg = self.fc2.backward(rec, &cache.g, dy)?;
        let du = gelu_backward(rec, &cache.u, &dg)?;
        self.fc1.backward(rec, &cache.x, &du)
    }

    /// The parameters' gradients alone (the first layer of a model needs no input gradient).
    pub fn param_grads(&self, rec: &mut Recorder, cache: &GeluMlpCache, dy: &Tensor) -> Result<()> {
        let dg = self.fc2.backward(rec, &cache.g, dy)?;
        let du = gelu_backward(rec, &cache.u, &dg)?;
        self.fc1.param_grads(rec, &cache.x, &du)
    }
}
