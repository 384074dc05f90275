//! Row gather. Kernels: `shaders/gather.wgsl`, and `shaders/gather_vec4.wgsl` on CPU devices.
//!
//! Tests: the harness's `gather` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/elementwise.rs` (with scatter-add, bad indices).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::{GATHER_INVERT, GATHER_MAIN, GATHER_VEC4_MAIN};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

pub(crate) use crate::kernels::params::GatherParams as RowParams;

/// Splits a tensor into (rows, width) with width the product of all but the first axis.
pub(crate) fn rows_width(t: &Tensor) -> Result<(usize, usize)> {
    match t.shape() {
        [] => Err(Error::Shape(format!("{t:?} has no row axis"))),
        [r, rest @ ..] => Ok((*r, rest.iter().product())),
    }
}

/// Whether rows of `width` floats are gathered a vec4 at a time (`gather_vec4.wgsl`): on CPU
/// devices (`Caps::cpu_kernels`), for widths of a multiple of 4. GPUs keep `gather.wgsl`.
fn vec4_rows(gpu: &crate::Gpu, width: usize) -> bool {
    gpu.caps().cpu_kernels && width.is_multiple_of(4) && gpu.supports(GATHER_VEC4_MAIN)
}

/// The gather kernels this device runs, for `velox info`.
pub fn variant(gpu: &crate::Gpu) -> &'static str {
    if vec4_rows(gpu, 4) {
        "a vec4 a step where rows are a multiple of 4 floats, 16 elements an invocation"
    } else {
        "an element an invocation"
    }
}

/// out[r] = src[idx[r]] for every r (rows are the first axis; idx is u32 of any shape whose
/// elements count the output rows). An index past src's rows gives a row of zeros.
pub fn gather(rec: &mut Recorder, src: &Tensor, idx: &Tensor) -> Result<Tensor> {
    gather_with(rec, src, idx, None)
}

/// `base + gather(src, idx)` in one pass (`base` f32 shaped like the gather's output): a
/// residual added as the rows come back from another order.
pub fn gather_plus(rec: &mut Recorder, src: &Tensor, idx: &Tensor, base: &Tensor) -> Result<Tensor> {
    gather_with(rec, src, idx, Some(base))
}

fn gather_with(rec: &mut Recorder, src: &Tensor, idx: &Tensor, base: Option<&Tensor>) -> Result<Tensor> {
    let (src_rows, width) = rows_width(src)?;
    if src.dtype() != DType::F32 || idx.dtype() != DType::U32 {
        return Err(Error::Shape(format!("gather needs f32 rows and u32 indices, got {src:?}, {idx:?}")));
    }
    let mut shape = vec![idx.numel()];
    shape.extend_from_slice(&src.shape()[1..]);
    if let Some(b) = base.filter(|b| b.shape() != shape.as_slice() || b.dtype() != DType::F32) {
        return Err(Error::Shape(format!("gather: the added rows {b:?} must be f32 {shape:?}")));
    }
    let out = Tensor::empty(src.gpu(), &shape, DType::F32)?;
    let total = out.numel();
    let fit = |v: usize| fit_u32(v, || format!("gather into {shape:?}"));
    let p = RowParams {
        rows: fit(idx.numel())?,
        width: fit(width)?,
        src_rows: fit(src_rows)?,
        add: base.is_some() as u32,
    };
    fit(total)?;
    // Without `base`, src stands in for the binding the kernel then does not read.
    let base = base.unwrap_or(src);
    if vec4_rows(src.gpu(), width) {
        let p = crate::kernels::params::GatherVec4Params { width: p.width / 4, ..bytemuck::cast(p) };
        let args = args::GatherVec4MainArgs { src, idx, out: &out, base };
        rec.dispatch_elements(GATHER_VEC4_MAIN, total as u64 / 4, args, &p)?;
    } else {
        rec.dispatch_elements(
            GATHER_MAIN,
            total as u64,
            args::GatherMainArgs { src, idx, out: &out, base },
            &p,
        )?;
    }
    Ok(out)
}

/// The inverse of a permutation `perm` (u32 `[n]` holding each of `0..n` once):
/// `inverse[perm[i]] = i`, so gathering by `perm` and then by `inverse` restores the order.
pub fn invert_permutation(rec: &mut Recorder, perm: &Tensor) -> Result<Tensor> {
    if perm.dtype() != DType::U32 || perm.shape().len() != 1 {
        return Err(Error::Shape(format!("invert_permutation needs u32 [n], got {perm:?}")));
    }
    let n = perm.numel();
    let fit = fit_u32(n, || format!("permutation of {n}"))?;
    let inverse = Tensor::empty(perm.gpu(), &[n], DType::U32)?;
    let p = RowParams { rows: fit, width: 1, src_rows: fit, add: 0 };
    rec.dispatch_linear(
        GATHER_INVERT,
        (n as u64).div_ceil(256),
        args::GatherInvertArgs { idx: perm, inverse: &inverse },
        &p,
    )?;
    Ok(inverse)
}

pub mod reference {
    pub fn invert_permutation(perm: &[u32]) -> Vec<u32> {
        let mut inv = vec![0; perm.len()];
        for (i, &p) in perm.iter().enumerate() {
            inv[p as usize] = i as u32;
        }
        inv
    }

    pub fn gather(src: &[f32], width: usize, idx: &[u32]) -> Vec<f64> {
        let rows = src.len().checked_div(width).unwrap_or(0);
        let mut out = Vec::with_capacity(idx.len() * width);
        for &i in idx {
            for c in 0..width {
                out.push(if (i as usize) < rows { src[i as usize * width + c] as f64 } else { 0.0 });
            }
        }
        out
    }
}
