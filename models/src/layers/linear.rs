//! Linear layer: `y = x @ W (+ b)`, `x [.., in]`, `W [in, out]`, `b [out]`.
//!
//! Backward: `dx = dy @ W^T`, `dW += x^T @ dy`, `db += sum over rows of dy`.

use velox_engine::ops::binary::{binary_into, Binary};
use velox_engine::ops::cast::cast;
use velox_engine::ops::matmul::{matmul, matmul_bias, matmul_into};
use velox_engine::ops::reduce::{reduce, Reduce};
use velox_engine::{DType, Precision, Recorder, Result, Tensor};

use super::{as_rows, expect_shape, Param};

pub struct Linear {
    /// `[in, out]`
    pub weight: Param,
    /// `[out]`
    pub bias: Option<Param>,
    pub in_features: usize,
    pub out_features: usize,
}

/// The input, kept for the weight gradient.
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
    /// way.
    pub fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, LinearCache)> {
        let x2 = as_rows("linear", x, self.in_features)?;
        let (xm, w) = match rec.precision() {
            Precision::F32 => (x2.clone(), self.weight.value.clone()),
            Precision::F16 => (cast(rec, &x2, DType::F16)?, self.weight.value_f16(rec)?),
        };
        // The bias is added by the matmul kernel as it writes (a separate pass where it cannot).
        let y = match &self.bias {
            Some(b) => matmul_bias(rec, &xm, &w, false, false, &b.value)?,
            None => matmul(rec, &xm, &w, false, false)?,
        };
        let mut y_shape = x.shape().to_vec();
        *y_shape.last_mut().unwrap() = self.out_features;
        Ok((y.reshape(&y_shape)?, LinearCache { x: x2, x_shape: x.shape().to_vec() }))
    }

    /// Adds `dW` (and `db`) into the gradients and returns `dx`.
    pub fn backward(&self, rec: &mut Recorder, cache: &LinearCache, dy: &Tensor) -> Result<Tensor> {
        self.param_grads(rec, cache, dy)?;
        let dy2 = as_rows("linear backward", dy, self.out_features)?;
        matmul(rec, &dy2, &self.weight.value, false, true)?.reshape(&cache.x_shape)
    }

    /// Adds `dW = x^T dy` and `db = sum_rows dy` into the gradients only (the first layer of a
    /// model needs no `dx`).
    pub fn param_grads(&self, rec: &mut Recorder, cache: &LinearCache, dy: &Tensor) -> Result<()> {
        let dy2 = as_rows("linear backward", dy, self.out_features)?;
        matmul_into(rec, &cache.x, &dy2, true, false, &self.weight.grad, true)?;
        if let Some(b) = &self.bias {
            let db = reduce(rec, &dy2, 0, Reduce::Sum)?;
            binary_into(rec, &b.grad, &db, &b.grad, Binary::Add)?;
        }
        Ok(())
    }

    /// `dx (+)= dy @ W^T` into an existing `dx` of the input's shape (`accumulate` adds, for an
    /// input that feeds several layers).
    pub fn input_grad_into(
        &self,
        rec: &mut Recorder,
        dy: &Tensor,
        dx: &Tensor,
        accumulate: bool,
    ) -> Result<()> {
        let dy2 = as_rows("linear backward", dy, self.out_features)?;
        let dx2 = as_rows("linear backward dx", dx, self.in_features)?;
        matmul_into(rec, &dy2, &self.weight.value, false, true, &dx2, accumulate)
    }
}
