//! f32 <-> f16 conversion. Kernel: `shaders/cast.wgsl` (packed halves, runs everywhere).
//!
//! Tests: the harness's `cast` row (`engine/tests/ops/cases.rs`: forward against the f64 reference
//! at awkward shapes); `engine/tests/ops/elementwise.rs` (round trips and extremes).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{CAST_F16_TO_F32, CAST_F32_TO_F16};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::fit_u32;
use crate::kernels::params::CastParams as Params;

/// A new tensor of the same shape converted to `dtype` (f32 <-> f16; same dtype copies).
/// f32 -> f16 rounds to nearest even; values beyond the f16 range become +-Inf, as in IEEE.
pub fn cast(rec: &mut Recorder, x: &Tensor, dtype: DType) -> Result<Tensor> {
    let out = Tensor::empty(x.gpu(), x.shape(), dtype)?;
    cast_into(rec, x, &out)?;
    Ok(out)
}

/// Converts `x` into `out` (same shape).
pub fn cast_into(rec: &mut Recorder, x: &Tensor, out: &Tensor) -> Result<()> {
    if x.shape() != out.shape() {
        return Err(Error::Shape(format!("cast {x:?} into {out:?}: shapes differ")));
    }
    let n = fit_u32(x.numel(), || format!("cast of {x:?}"))?;
    let words = (n as u64).div_ceil(2);
    let params = Params { n };
    match (x.dtype(), out.dtype()) {
        (a, b) if a == b => rec.copy(x, out),
        (DType::F32, DType::F16) => rec.dispatch_elements(
            CAST_F32_TO_F16,
            words as u64,
            args::CastF32ToF16Args { src_f32: x, dst_f16: out },
            &params,
        ),
        (DType::F16, DType::F32) => rec.dispatch_elements(
            CAST_F16_TO_F32,
            words as u64,
            args::CastF16ToF32Args { src_f16: x, dst_f32: out },
            &params,
        ),
        (a, b) => Err(Error::Shape(format!("cast from {} to {} is not supported", a.name(), b.name()))),
    }
}

pub mod reference {
    /// f32 -> f16 -> f64, round to nearest even (the `half` crate's conversion).
    pub fn to_f16(x: &[f32]) -> Vec<f64> {
        x.iter().map(|&v| half::f16::from_f32(v).to_f64()).collect()
    }
}
