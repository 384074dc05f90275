//! Fill a tensor with one value. Kernel: `shaders/fill.wgsl`.
//!
//! Tests: `engine/tests/ops/fill_copy.rs` (every dtype, awkward sizes, ordering with copies).

use crate::error::Result;
use crate::kernels::args;
use crate::kernels::FILL_MAIN;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::kernels::params::FillParams as Params;

/// Sets every element of `t` to `value` (converted to the tensor's dtype).
pub fn fill(rec: &mut Recorder, t: &Tensor, value: f64) -> Result<()> {
    let bits = match t.dtype() {
        DType::F32 => (value as f32).to_bits(),
        DType::U32 => value as u32,
        DType::I32 => (value as i32) as u32,
        DType::F16 => {
            let h = half::f16::from_f64(value).to_bits() as u32;
            h | (h << 16)
        }
    };
    fill_bits(rec, t, bits)
}

/// Sets every 32-bit word of `t`'s storage to `bits`.
pub fn fill_bits(rec: &mut Recorder, t: &Tensor, bits: u32) -> Result<()> {
    let words = t.bytes().div_ceil(4);
    let params = Params { words: u32::try_from(words).map_err(|_| too_many(t))?, value: bits };
    rec.dispatch_elements(FILL_MAIN, words, args::FillMainArgs { data: t }, &params)
}

fn too_many(t: &Tensor) -> crate::Error {
    crate::Error::too_large(crate::Limit::Index, format!("{t:?} has more than 2^32 words"))
}
