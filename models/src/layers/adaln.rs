//! adaLN modulation (DiT, adaLN-Zero): per-sample shift, scale and gate, broadcast over the
//! tokens of each sample. `x [B, T, D]`; `shift`, `scale`, `gate [B, D]`.
//!
//! - [`Modulate`]: `y = x * (1 + scale) + shift`;
//!   backward `dx = dy * (1 + scale)`, `dshift = sum_t dy`, `dscale = sum_t dy * x`.
//! - [`GatedResidual`]: `out = res + gate * y`;
//!   backward `dres = dout`, `dgate = sum_t dout * y`, `dy = dout * gate`.

use velox_engine::ops::binary::{binary, binary_into, Binary};
use velox_engine::ops::reduce::{reduce, Reduce};
use velox_engine::ops::unary::{unary, Unary};
use velox_engine::{DType, Error, Recorder, Result, Tensor};

/// `[B, T, D]` and `[B, D]` agree; returns the per-sample tensor as `[B, 1, D]`.
fn per_sample(what: &str, x: &Tensor, s: &Tensor) -> Result<Tensor> {
    let xs = x.shape();
    if x.dtype() != DType::F32 || s.dtype() != DType::F32 || xs.len() != 3 || s.shape() != [xs[0], xs[2]] {
        return Err(Error::Shape(format!("{what}: needs f32 x [B, T, D] and [B, D], got {x:?} and {s:?}")));
    }
    s.reshape(&[xs[0], 1, xs[2]])
}

/// `y = x * (1 + scale) + shift`.
pub struct Modulate;

#[derive(Clone, Debug)]
pub struct ModulateCache {
    x: Tensor,
    /// `1 + scale` as `[B, 1, D]`.
    one_plus_scale: Tensor,
}

pub struct ModulateGrads {
    pub dx: Tensor,
    pub dshift: Tensor,
    pub dscale: Tensor,
}

impl Modulate {
    pub fn forward(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        shift: &Tensor,
        scale: &Tensor,
    ) -> Result<(Tensor, ModulateCache)> {
        let shift = per_sample("modulate shift", x, shift)?;
        let scale = per_sample("modulate scale", x, scale)?;
        let one_plus_scale = unary(rec, &scale, Unary::Affine(1.0, 1.0))?;
        let y = binary(rec, x, &one_plus_scale, Binary::Mul)?;
        binary_into(rec, &y, &shift, &y, Binary::Add)?;
        Ok((y, ModulateCache { x: x.clone(), one_plus_scale }))
    }

    pub fn backward(&self, rec: &mut Recorder, cache: &ModulateCache, dy: &Tensor) -> Result<ModulateGrads> {
        let dx = binary(rec, dy, &cache.one_plus_scale, Binary::Mul)?;
        let dshift = reduce(rec, dy, 1, Reduce::Sum)?;
        let dy_x = binary(rec, dy, &cache.x, Binary::Mul)?;
        let dscale = reduce(rec, &dy_x, 1, Reduce::Sum)?;
        Ok(ModulateGrads { dx, dshift, dscale })
    }
}

/// `out = res + gate * y`.
pub struct GatedResidual;

#[derive(Clone, Debug)]
pub struct GatedResidualCache {
    /// `[B, 1, D]`
    gate: Tensor,
    y: Tensor,
}

pub struct GatedResidualGrads {
    /// The incoming gradient itself (shared storage, not a copy): do not write it in place.
    pub dres: Tensor,
    pub dgate: Tensor,
    pub dy: Tensor,
}

impl GatedResidual {
    pub fn forward(
        &self,
        rec: &mut Recorder,
        res: &Tensor,
        gate: &Tensor,
        y: &Tensor,
    ) -> Result<(Tensor, GatedResidualCache)> {
        let gate = per_sample("gated residual gate", y, gate)?;
        if res.shape() != y.shape() {
            return Err(Error::Shape(format!("gated residual: res {res:?} and y {y:?} differ")));
        }
        let out = binary(rec, y, &gate, Binary::Mul)?;
        binary_into(rec, &out, res, &out, Binary::Add)?;
        Ok((out, GatedResidualCache { gate, y: y.clone() }))
    }

    pub fn backward(
        &self,
        rec: &mut Recorder,
        cache: &GatedResidualCache,
        dout: &Tensor,
    ) -> Result<GatedResidualGrads> {
        let dy = binary(rec, dout, &cache.gate, Binary::Mul)?;
        let dout_y = binary(rec, dout, &cache.y, Binary::Mul)?;
        let dgate = reduce(rec, &dout_y, 1, Reduce::Sum)?;
        Ok(GatedResidualGrads { dres: dout.clone(), dgate, dy })
    }
}
