//! Copies of column blocks between row-major matrices. Kernel: `shaders/columns.wgsl`.
//!
//! Tests: the harness's `columns` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/elementwise.rs` (the permutation's inverse, bad
//! ranges).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::COLUMNS_MAIN;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::fit_u32;
use crate::kernels::params::ColumnsParams as Params;

fn matrix(t: &Tensor, what: &str) -> Result<(usize, usize)> {
    match (t.dtype(), t.shape()) {
        (DType::F32, &[r, c]) => Ok((r, c)),
        _ => Err(Error::Shape(format!("copy_columns: {what} must be an f32 matrix, got {t:?}"))),
    }
}

/// `dst[:, dst_col..dst_col + count] = scale * src[:, src_col..src_col + count]`.
pub fn copy_columns(
    rec: &mut Recorder,
    src: &Tensor,
    src_col: usize,
    dst: &Tensor,
    dst_col: usize,
    count: usize,
    scale: f32,
) -> Result<()> {
    let (rows, src_width) = matrix(src, "src")?;
    let (dst_rows, dst_width) = matrix(dst, "dst")?;
    if rows != dst_rows || src_col + count > src_width || dst_col + count > dst_width {
        return Err(Error::Shape(format!(
            "copy_columns: {count} columns from {src_col} of {src:?} to {dst_col} of {dst:?} do not fit"
        )));
    }
    let total = fit_u32(rows * count, || format!("copy_columns of {src:?}"))?;
    let p = Params {
        rows: rows as u32,
        count: count as u32,
        src_width: src_width as u32,
        src_col: src_col as u32,
        dst_width: dst_width as u32,
        dst_col: dst_col as u32,
        scale,
    };
    rec.dispatch_elements(COLUMNS_MAIN, total as u64, args::ColumnsMainArgs { src, dst }, &p)
}

/// A new `[rows, count]` matrix of `scale * src[:, col..col + count]`.
pub fn columns(rec: &mut Recorder, src: &Tensor, col: usize, count: usize, scale: f32) -> Result<Tensor> {
    let (rows, _) = matrix(src, "src")?;
    let out = Tensor::empty(src.gpu(), &[rows, count], DType::F32)?;
    copy_columns(rec, src, col, &out, 0, count, scale)?;
    Ok(out)
}

pub mod reference {
    /// `scale * src[:, col..col + count]` of a `[rows, width]` matrix.
    pub fn columns(src: &[f32], width: usize, col: usize, count: usize, scale: f32) -> Vec<f64> {
        src.chunks(width.max(1))
            .flat_map(|row| row[col..col + count].iter().map(move |&v| scale as f64 * v as f64))
            .collect()
    }
}
