//! The layers the Velox models are built from, each with its forward and its backward next to
//! each other, as in llm.c: gradients are wired by hand, not by a tape.
//!
//! Every layer has `forward(&self, rec, x, ..) -> Result<(y, Cache)>` and
//! `backward(&self, rec, &cache, dy) -> Result<dx>`. The backward *adds* parameter gradients
//! into each [`Param`]'s `grad` (so a parameter used twice sums its two gradients); zero them
//! before a step. The kernels live in the engine (`engine/src/ops`), the f64 references of the
//! layers built from several ops in [`reference`].

pub mod adaln;
pub mod attention;
pub mod feedforward;
pub mod fourier;
pub mod linear;
pub mod loss;
pub mod norm;
pub mod reference;
pub mod residual;

use velox_engine::ops::cast::cast;
use velox_engine::ops::fill::fill;
use velox_engine::{DType, Error, Gpu, Recorder, Result, Tensor};

pub use adaln::{GatedResidual, Modulate};
pub use attention::MultiHeadAttention;
pub use feedforward::{GeluMlp, SwiGlu};
pub use fourier::Fourier;
pub use linear::Linear;
pub use loss::Loss;
pub use norm::{LayerNorm, RmsNorm};
pub use residual::Residual;

/// A layer that maps `x [.., in]` to `y [.., out]` and back: what every single-input layer
/// here offers, so generic code (benchmarks, stacks) can drive any of them.
pub trait Layer {
    /// What the backward pass needs from the forward pass.
    type Cache;
    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, Self::Cache)>;
    /// Adds the parameter gradients and returns `dx`.
    fn backward(&self, rec: &mut Recorder, cache: &Self::Cache, dy: &Tensor) -> Result<Tensor>;
}

macro_rules! layer {
    ($($t:ty => $cache:ty),* $(,)?) => {$(
        impl Layer for $t {
            type Cache = $cache;
            fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, $cache)> {
                <$t>::forward(self, rec, x)
            }
            fn backward(&self, rec: &mut Recorder, cache: &$cache, dy: &Tensor) -> Result<Tensor> {
                <$t>::backward(self, rec, cache, dy)
            }
        }
    )*};
}

layer!(
    Linear => linear::LinearCache,
    RmsNorm => norm::RmsNormCache,
    LayerNorm => norm::LayerNormCache,
    SwiGlu => feedforward::SwiGluCache,
    GeluMlp => feedforward::GeluMlpCache,
    Fourier => fourier::FourierCache,
);

/// A trainable tensor and its gradient, of one shape. Both are plain f32 tensors: their own
/// buffers, or views into a parameter store's one big buffer.
#[derive(Clone, Debug)]
pub struct Param {
    pub value: Tensor,
    pub grad: Tensor,
    /// An f16 copy of `value` for the f16 path (a store's, see
    /// [`crate::params::ParamStore::sync_half`]); without one, the f16 path rounds `value` as
    /// it goes.
    pub half: Option<Tensor>,
}

impl Param {
    /// A parameter with its own storage, holding `init`, with a zero gradient.
    pub fn new(gpu: &Gpu, shape: &[usize], init: &[f32]) -> Result<Param> {
        let value = Tensor::from_slice(gpu, shape, init)?;
        let grad = Tensor::from_slice(gpu, shape, &vec![0.0f32; init.len()])?;
        Ok(Param { value, grad, half: None })
    }

    /// A parameter from existing tensors (for example views of a parameter store).
    pub fn from_tensors(value: Tensor, grad: Tensor) -> Result<Param> {
        if value.dtype() != DType::F32 || grad.dtype() != DType::F32 || value.shape() != grad.shape() {
            return Err(Error::Shape(format!(
                "a parameter needs f32 value and grad of one shape: {value:?}, {grad:?}"
            )));
        }
        Ok(Param { value, grad, half: None })
    }

    /// A parameter that is never trained (a pretrained network's weights): its gradient is an
    /// empty tensor, so a backward pass through it fails on the shape instead of writing.
    pub fn frozen(gpu: &Gpu, shape: &[usize], value: &[f32]) -> Result<Param> {
        let value = Tensor::from_slice(gpu, shape, value)?;
        Ok(Param { value, grad: Tensor::empty(gpu, &[0], DType::F32)?, half: None })
    }

    pub fn shape(&self) -> &[usize] {
        self.value.shape()
    }

    /// The parameter `name` of a parameter store: views of its value and gradient buffers.
    pub fn from_store(store: &crate::params::ParamStore, name: &str) -> Result<Param> {
        let p = Param::from_tensors(store.param(name)?.clone(), store.grad(name)?.clone())?;
        Ok(Param { half: Some(store.param_half(name)?.clone()), ..p })
    }

    /// The value as f16: the copy when there is one, else rounded now, in `rec`.
    pub fn value_f16(&self, rec: &mut Recorder) -> Result<Tensor> {
        match &self.half {
            Some(h) => Ok(h.clone()),
            None => cast(rec, &self.value, DType::F16),
        }
    }

    /// Sets the gradient to zero.
    pub fn zero_grad(&self, rec: &mut Recorder) -> Result<()> {
        fill(rec, &self.grad, 0.0)
    }
}

/// Fails unless `p` has `shape`.
pub(crate) fn expect_shape(what: &str, p: &Param, shape: &[usize]) -> Result<()> {
    if p.shape() != shape {
        return Err(Error::Shape(format!("{what}: expected shape {shape:?}, got {:?}", p.shape())));
    }
    Ok(())
}

/// `x` viewed as `[rows, width]` with `width` its last axis.
pub(crate) fn as_rows(what: &str, x: &Tensor, width: usize) -> Result<Tensor> {
    if x.dtype() != DType::F32 || x.shape().last() != Some(&width) {
        return Err(Error::Shape(format!("{what}: input must be f32 with last axis {width}, got {x:?}")));
    }
    x.reshape(&[x.numel().checked_div(width).unwrap_or(0), width])
}
