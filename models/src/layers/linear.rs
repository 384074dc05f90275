//! Linear layer: `y = x @ W (+ b)`, `x [.., in]`, `W [in, out]`, `b [out]`.
//!
//! Backward: `dx = dy @ W^T`, `dW += x^T @ dy`, `db += sum over rows of dy`.
//!
//! Tests: `tests/models/layers.rs` (against the reference, stacks, f16 operands, finite
//! differences).

use velox_engine::ops::cast::cast;
use velox_engine::ops::matmul::{matmul, matmul_bias, matmul_bias_into, matmul_into, matmul_sum_into};
use velox_engine::ops::reduce::{reduce_into, Reduce};
use velox_engine::{DType, Precision, Recorder, Result, Tensor};

use super::{as_rows, expect_shape, Param};

/// The operands a product reads in `rec`'s precision: `x` (as rows) and the weight, as they
/// are in f32, or `x` rounded to f16 and the weight's f16 copy.
fn operands(rec: &mut Recorder, x2: &Tensor, weight: &Param) -> Result<(Tensor, Tensor)> {
    match rec.precision() {
        Precision::F32 => Ok((x2.clone(), weight.value.clone())),
        Precision::F16 => Ok((cast(rec, x2, DType::F16)?, weight.value_f16(rec)?)),
    }
}

/// `x @ W (+ bias)`, the bias added by the product as it writes (a separate pass where the
/// kernel cannot).
fn biased(rec: &mut Recorder, x: &Tensor, w: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    match bias {
        Some(b) => matmul_bias(rec, x, w, false, false, b),
        None => matmul(rec, x, w, false, false),
    }
}

/// What a backward pass's products read: `dy` as the forward pass's product read its input
/// (rounded to f16 after an f16 forward pass), and the weight alike when `dx` is wanted.
fn gradient_operands(
    rec: &mut Recorder,
    cache: &LinearCache,
    dy: &Tensor,
    weight: &Param,
    want_dx: bool,
) -> Result<(Tensor, Option<Tensor>)> {
    match cache.x.dtype() {
        DType::F16 => Ok((cast(rec, dy, DType::F16)?, want_dx.then(|| weight.value_f16(rec)).transpose()?)),
        _ => Ok((dy.clone(), Some(weight.value.clone()))),
    }
}

pub struct Linear {
    /// `[in, out]`
    pub weight: Param,
    /// `[out]`
    pub bias: Option<Param>,
    pub in_features: usize,
    pub out_features: usize,
}

/// The input, kept for the weight gradient: as the product read it, f32, or rounded to f16 in
/// an f16 recording.
#[derive(Clone, Debug)]
pub struct LinearCache {
    /// `x` as `[rows, in]`.
    x: Tensor,
    /// The shape of `x` as given.
    x_shape: Vec<usize>,
}

impl Linear {
    pub fn new(weight: Param, bias: Option<Param>) -> Result<Linear> {
        let shape = weight.shape().to_vec();
        if shape.len() != 2 {
            return Err(velox_engine::Error::Shape(format!(
                "linear weight must be [in, out], got {shape:?}"
            )));
        }
        if let Some(b) = &bias {
            expect_shape("linear bias", b, &[shape[1]])?;
        }
        Ok(Linear { weight, bias, in_features: shape[0], out_features: shape[1] })
    }

    /// `y [.., out]` for `x [.., in]`. In an f16 recording (see [`Precision`]) the product reads
    /// `x` rounded to f16 and the weight's f16 copy, and accumulates in f32; `y` is f32 either
    /// way. The backward pass of an f16 forward pass is f16 too (see [`Linear::backward`]).
    pub fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, LinearCache)> {
        self.forward_with(rec, x, None)
    }

    /// `y = residual + x @ W (+ b)` in one product (the residual copied into the output, the
    /// product added onto it): a residual block's output without a separate add.
    pub fn forward_plus(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        residual: &Tensor,
    ) -> Result<(Tensor, LinearCache)> {
        self.forward_with(rec, x, Some(residual))
    }

    fn forward_with(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        residual: Option<&Tensor>,
    ) -> Result<(Tensor, LinearCache)> {
        let x2 = as_rows("linear", x, self.in_features)?;
        let mut y_shape = x.shape().to_vec();
        *y_shape.last_mut().unwrap() = self.out_features;
        if let Some(r) = residual.filter(|r| r.shape() != y_shape.as_slice() || r.dtype() != DType::F32) {
            return Err(velox_engine::Error::Shape(format!(
                "linear: the residual {r:?} must be f32 {y_shape:?}"
            )));
        }
        let (xm, w) = operands(rec, &x2, &self.weight)?;
        let bias = self.bias.as_ref().map(|b| &b.value);
        let y = match residual {
            Some(r) => {
                let y = Tensor::empty(x.gpu(), &[x2.shape()[0], self.out_features], DType::F32)?;
                rec.copy(r, &y)?;
                matmul_bias_into(rec, &xm, &w, false, false, bias, &y, true)?;
                y
            }
            None => biased(rec, &xm, &w, bias)?,
        };
        Ok((y.reshape(&y_shape)?, LinearCache { x: xm, x_shape: x.shape().to_vec() }))
    }

    /// Adds `dW` (and `db`) into the gradients and returns `dx`. After an f16 forward pass the
    /// products read `dy` rounded to f16 (`dW += x16^T dy16`, `dx = dy16 W16^T`, f32
    /// accumulation, as mixed-precision training does); `db` sums the f32 `dy`.
    pub fn backward(&self, rec: &mut Recorder, cache: &LinearCache, dy: &Tensor) -> Result<Tensor> {
        let dx = Tensor::empty(dy.gpu(), &[cache.x.shape()[0], self.in_features], DType::F32)?;
        self.grads(rec, cache, dy, Some((&dx, false)))?;
        dx.reshape(&cache.x_shape)
    }

    /// Adds `dW = x^T dy` and `db = sum_rows dy` into the gradients only (the first layer of a
    /// model needs no `dx`).
    pub fn param_grads(&self, rec: &mut Recorder, cache: &LinearCache, dy: &Tensor) -> Result<()> {
        self.grads(rec, cache, dy, None)
    }

    /// Adds the parameter gradients and writes `dx = dy @ W^T` into an existing tensor of the
    /// input's shape, or adds it there (`accumulate`: an input that feeds several layers).
    pub fn grads_into(
        &self,
        rec: &mut Recorder,
        cache: &LinearCache,
        dy: &Tensor,
        dx: &Tensor,
        accumulate: bool,
    ) -> Result<()> {
        self.grads(rec, cache, dy, Some((dx, accumulate)))
    }

    fn grads(
        &self,
        rec: &mut Recorder,
        cache: &LinearCache,
        dy: &Tensor,
        dx: Option<(&Tensor, bool)>,
    ) -> Result<()> {
        let dy2 = as_rows("linear backward", dy, self.out_features)?;
        let (dym, w) = gradient_operands(rec, cache, &dy2, &self.weight, dx.is_some())?;
        matmul_into(rec, &cache.x, &dym, true, false, &self.weight.grad, true)?;
        if let Some(b) = &self.bias {
            reduce_into(rec, &dy2, 0, Reduce::Sum, &b.grad, true)?;
        }
        if let (Some((dx, accumulate)), Some(w)) = (dx, w) {
            let dx2 = as_rows("linear backward dx", dx, self.in_features)?;
            matmul_into(rec, &dym, &w, false, true, &dx2, accumulate)?;
        }
        Ok(())
    }
}

/// `k` linear layers that read the same input, their weights `[k, in, out]` and biases
/// `[k, out]` stacked in one tensor each (parameters that lie one after another in a store,
/// [`crate::params::ParamStore::stacked`]): the k products are one batched product, the k
/// weight gradients another, the bias gradients one sum. An adaLN block's six modulations take
/// 2 dispatches forward and 4 backward this way instead of 6 and 18.
pub struct LinearStack {
    /// `[k, in, out]`
    pub weight: Param,
    /// `[k, out]`
    pub bias: Option<Param>,
    pub k: usize,
    pub in_features: usize,
    pub out_features: usize,
}

impl LinearStack {
    pub fn new(weight: Param, bias: Option<Param>) -> Result<LinearStack> {
        let shape = weight.shape().to_vec();
        if shape.len() != 3 {
            return Err(velox_engine::Error::Shape(format!(
                "stacked linear weights must be [k, in, out], got {shape:?}"
            )));
        }
        if let Some(b) = &bias {
            expect_shape("stacked linear biases", b, &[shape[0], shape[2]])?;
        }
        Ok(LinearStack { weight, bias, k: shape[0], in_features: shape[1], out_features: shape[2] })
    }

    /// Whether the outputs over `x`'s rows split into views of one layer's output each in a
    /// recording of `precision`: the device's offset alignment divides the bytes of `rows *
    /// out` elements, counted as f16 in an f16 recording (whose passes split f16 tensors too,
    /// the rounded outputs and gradients) and as f32 otherwise. Where they do not, use the
    /// layers one by one. Forward and backward passes are recorded in one precision, so they
    /// decide alike. (Alignments run from 4 bytes to 256: SwiftShader's 256 refuses stacks that
    /// lavapipe's 16 allows.)
    pub fn fits(&self, x: &Tensor, precision: Precision) -> bool {
        let rows = x.numel() / self.in_features.max(1);
        let align = x.gpu().caps().min_storage_buffer_offset_alignment.max(4) as usize;
        let size = match precision {
            Precision::F16 => DType::F16.size(),
            Precision::F32 => DType::F32.size(),
        };
        (rows * self.out_features * size).is_multiple_of(align)
    }

    /// The layers' parts `[rows, out]` of a stacked `[k, rows, out]` tensor (the forward pass's
    /// output, or a gradient laid out like it), as views.
    pub fn parts(&self, y: &Tensor) -> Result<Vec<Tensor>> {
        let rows = y.numel() / (self.k * self.out_features).max(1);
        let chunk = rows * self.out_features;
        (0..self.k).map(|i| y.view(i * chunk, &[rows, self.out_features])).collect()
    }

    /// `y [k, rows, out]` for `x [rows, in]`: layer i's output is `y[i]`. Precision as in
    /// [`Linear::forward`].
    pub fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, LinearCache)> {
        let x2 = as_rows("stacked linear", x, self.in_features)?;
        let (xm, w) = operands(rec, &x2, &self.weight)?;
        // Each layer's bias ([k, out]) onto its own output.
        let y = biased(rec, &xm, &w, self.bias.as_ref().map(|b| &b.value))?;
        Ok((y, LinearCache { x: xm, x_shape: x.shape().to_vec() }))
    }

    /// Adds the gradients for `dy [k, rows, out]` and, with `dx`, writes `dx = sum_i dy[i]
    /// W[i]^T` there (or adds it, `accumulate`).
    pub fn grads_into(
        &self,
        rec: &mut Recorder,
        cache: &LinearCache,
        dy: &Tensor,
        dx: Option<(&Tensor, bool)>,
    ) -> Result<()> {
        let rows = cache.x.shape()[0];
        let expect = [self.k, rows, self.out_features];
        if dy.dtype() != DType::F32 || dy.shape() != expect {
            return Err(velox_engine::Error::Shape(format!(
                "stacked linear backward: dy must be f32 {expect:?}, got {dy:?}"
            )));
        }
        let (dym, w) = gradient_operands(rec, cache, dy, &self.weight, dx.is_some())?;
        matmul_into(rec, &cache.x, &dym, true, false, &self.weight.grad, true)?;
        if let Some(b) = &self.bias {
            reduce_into(rec, dy, 1, Reduce::Sum, &b.grad, true)?;
        }
        if let (Some((dx, accumulate)), Some(w)) = (dx, w) {
            let dx2 = as_rows("stacked linear backward dx", dx, self.in_features)?;
            matmul_sum_into(rec, &dym, &w, false, true, &dx2, accumulate)?;
        }
        Ok(())
    }
}
