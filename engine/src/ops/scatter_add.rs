//! Row scatter-add. Kernels: `shaders/scatter_add.wgsl` (native f32 atomics) and
//! `shaders/scatter_add_cas.wgsl` (compare-and-swap fallback), chosen by the device.
//!
//! Tests: the harness's `scatter_add` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/elementwise.rs` (the compare-and-swap path,
//! determinism).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::params::ScatterAddBodyParams as Params;
use crate::kernels::{SCATTER_ADD_CAS_MAIN, SCATTER_ADD_MAIN};
use crate::ops::gather::rows_width;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// Which kernel this device uses.
pub fn variant(gpu: &crate::Gpu) -> &'static str {
    if gpu.supports(SCATTER_ADD_MAIN) {
        "f32 atomic add"
    } else {
        "compare-and-swap loop (no f32 atomics)"
    }
}

/// out[idx[r]] += src[r] for every row r of src (rows are the first axis). Indices past out's
/// rows are skipped. The order of additions into one row is unspecified, so where an index
/// repeats, sums may differ in the last bits between runs; with distinct indices each row takes
/// one addition and the result is exact and repeatable.
pub fn scatter_add(rec: &mut Recorder, src: &Tensor, idx: &Tensor, out: &Tensor) -> Result<()> {
    let (rows, width) = rows_width(src)?;
    let (dst_rows, dst_width) = rows_width(out)?;
    if src.dtype() != DType::F32 || out.dtype() != DType::F32 || idx.dtype() != DType::U32 {
        return Err(Error::Shape(format!(
            "scatter_add needs f32 rows and u32 indices: {src:?}, {idx:?}, {out:?}"
        )));
    }
    if idx.numel() != rows || width != dst_width {
        return Err(Error::Shape(format!(
            "scatter_add: {} indices for {rows} source rows; source rows of {width}, destination rows of {dst_width}",
            idx.numel()
        )));
    }
    let fit = |v: usize| fit_u32(v, || format!("scatter_add of {src:?}"));
    fit(src.numel())?;
    fit(out.numel())?;
    let p = Params { rows: fit(rows)?, width: fit(width)?, dst_rows: fit(dst_rows)?, _add: 0 };
    let kernel = if rec_supports(rec, SCATTER_ADD_MAIN) { SCATTER_ADD_MAIN } else { SCATTER_ADD_CAS_MAIN };
    rec.dispatch_linear(
        kernel,
        (src.numel() as u64).div_ceil(256),
        args::ScatterAddMainArgs { src, idx, out },
        &p,
    )
}

/// Forces the compare-and-swap kernel (to test the fallback on devices that have atomics).
pub fn scatter_add_cas(rec: &mut Recorder, src: &Tensor, idx: &Tensor, out: &Tensor) -> Result<()> {
    let (rows, width) = rows_width(src)?;
    let (dst_rows, _) = rows_width(out)?;
    let fit = |v: usize| fit_u32(v, || format!("scatter_add of {src:?}"));
    let p = Params { rows: fit(rows)?, width: fit(width)?, dst_rows: fit(dst_rows)?, _add: 0 };
    rec.dispatch_linear(
        SCATTER_ADD_CAS_MAIN,
        (src.numel() as u64).div_ceil(256),
        args::ScatterAddCasMainArgs { src, idx, out },
        &p,
    )
}

fn rec_supports(rec: &Recorder, k: impl Into<crate::kernels::KernelId>) -> bool {
    rec.gpu().supports(k)
}

pub mod reference {
    pub fn scatter_add(src: &[f32], width: usize, idx: &[u32], out: &[f32]) -> Vec<f64> {
        let mut acc: Vec<f64> = out.iter().map(|&v| v as f64).collect();
        let dst_rows = out.len().checked_div(width).unwrap_or(0);
        for (r, &i) in idx.iter().enumerate() {
            if (i as usize) < dst_rows {
                for c in 0..width {
                    acc[i as usize * width + c] += src[r * width + c] as f64;
                }
            }
        }
        acc
    }
}
