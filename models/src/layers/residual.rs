//! Residual add `y = x + f(x)`; its backward hands `dy` to both branches.
//!
//! Tests: `tests/models/layers.rs` (gradients to both branches).

use velox_engine::ops::binary::{binary, Binary};
use velox_engine::{Error, Recorder, Result, Tensor};

pub struct Residual;

impl Residual {
    /// `y = x + fx` (no cache: the backward needs nothing).
    pub fn forward(&self, rec: &mut Recorder, x: &Tensor, fx: &Tensor) -> Result<(Tensor, ())> {
        if x.shape() != fx.shape() {
            return Err(Error::Shape(format!("residual: {x:?} and {fx:?} differ")));
        }
        Ok((binary(rec, x, fx, Binary::Add)?, ()))
    }

    /// `(dx, dfx)`: both are `dy` itself (shared storage, not copies): do not write them in place.
    pub fn backward(&self, _rec: &mut Recorder, _cache: &(), dy: &Tensor) -> Result<(Tensor, Tensor)> {
        Ok((dy.clone(), dy.clone()))
    }
}
