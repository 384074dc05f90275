//! adaLN modulation (DiT, adaLN-Zero): per-sample shift, scale and gate, broadcast over the
//! tokens of each sample. `x [B, T, D]`; `shift`, `scale`, `gate [B, D]`.
//!
//! - [`Modulate`]: `y = x * (1 + scale) + shift`;
//!   backward `dx = dy * (1 + scale)`, `dshift = sum_t dy`, `dscale = sum_t dy * x`.
//! - [`GatedResidual`]: `out = res + gate * y`;
//!   backward `dres = dout`, `dgate = sum_t dout * y`, `dy = dout * gate`.
//!
//! Tests: `tests/models/layers.rs` (against the reference, the gated residual) and the engine's
//! harness row of adaLN.

use velox_engine::ops::adaln;
use velox_engine::ops::reduce::{reduce, Reduce};
use velox_engine::{Recorder, Result, Tensor};

/// The per-sample gradient `[B, D]` of a `[B, T, D]` one: summed over T (a view when T = 1).
fn per_sample_sum(rec: &mut Recorder, g: &Tensor) -> Result<Tensor> {
    let s = g.shape();
    match s[1] {
        1 => g.reshape(&[s[0], s[2]]),
        _ => reduce(rec, g, 1, Reduce::Sum),
    }
}

/// `y = x * (1 + scale) + shift`.
pub struct Modulate;

#[derive(Clone, Debug)]
pub struct ModulateCache {
    x: Tensor,
    scale: Tensor,
}

pub struct ModulateGrads {
    pub dx: Tensor,
    /// `dy` summed over T: a view of `dy` itself when T = 1 (do not write it in place).
    pub dshift: Tensor,
    pub dscale: Tensor,
}

impl Modulate {
    /// One pass ([`adaln::modulate`]).
    pub fn forward(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        shift: &Tensor,
        scale: &Tensor,
    ) -> Result<(Tensor, ModulateCache)> {
        let y = adaln::modulate(rec, x, scale, shift)?;
        Ok((y, ModulateCache { x: x.clone(), scale: scale.clone() }))
    }

    /// One pass when T = 1; two more sums otherwise.
    pub fn backward(&self, rec: &mut Recorder, cache: &ModulateCache, dy: &Tensor) -> Result<ModulateGrads> {
        let (dx, dy_x) = adaln::backward(rec, &cache.x, &cache.scale, dy, 1.0)?;
        Ok(ModulateGrads { dx, dshift: per_sample_sum(rec, dy)?, dscale: per_sample_sum(rec, &dy_x)? })
    }
}

/// `out = res + gate * y`.
pub struct GatedResidual;

#[derive(Clone, Debug)]
pub struct GatedResidualCache {
    /// `[B, D]`
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
    /// One pass ([`adaln::gate`]).
    pub fn forward(
        &self,
        rec: &mut Recorder,
        res: &Tensor,
        gate: &Tensor,
        y: &Tensor,
    ) -> Result<(Tensor, GatedResidualCache)> {
        let out = adaln::gate(rec, y, gate, res)?;
        Ok((out, GatedResidualCache { gate: gate.clone(), y: y.clone() }))
    }

    /// One pass when T = 1; one more sum otherwise.
    pub fn backward(
        &self,
        rec: &mut Recorder,
        cache: &GatedResidualCache,
        dout: &Tensor,
    ) -> Result<GatedResidualGrads> {
        let (dy, dout_y) = adaln::backward(rec, &cache.y, &cache.gate, dout, 0.0)?;
        Ok(GatedResidualGrads { dres: dout.clone(), dgate: per_sample_sum(rec, &dout_y)?, dy })
    }
}
