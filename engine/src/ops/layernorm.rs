//! LayerNorm over the last axis, with or without the affine `w`, `b`. Kernel:
//! `shaders/layernorm.wgsl`.
//!
//! `y = (x - mean) / sqrt(var + eps) * w + b`. The forward saves the per-row `mean` and `rstd`
//! for the backward, which gives `dx` and adds `dw`, `db` into gradient tensors.
//!
//! Tests: the harness's `layernorm` row (`engine/tests/ops/cases.rs`: forward and backward, the
//! reference against finite differences against the f64 reference at awkward shapes);
//! `tests/models/layers.rs` (stability at large, tiny and constant rows).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{
    LAYERNORM_WG256_BACKWARD, LAYERNORM_WG256_FORWARD, LAYERNORM_WG256_PARAM_GRADS, LAYERNORM_WG8_BACKWARD,
    LAYERNORM_WG8_FORWARD,
};
use crate::ops::rmsnorm::{add_partials, check_residual, check_vector, chunking, rows_and_width, RowShape};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::kernels::params::LayernormParams as Params;

/// What the forward saves for the backward.
#[derive(Clone, Debug)]
pub struct LayerNormOut {
    pub y: Tensor,
    /// Per row (shape of `x` without its last axis).
    pub mean: Tensor,
    pub rstd: Tensor,
}

/// LayerNorm of every row of `x` (last axis `width`); `affine` is `(w, b)`, each of `width`.
pub fn layernorm(
    rec: &mut Recorder,
    x: &Tensor,
    width: usize,
    affine: Option<(&Tensor, &Tensor)>,
    eps: f32,
) -> Result<LayerNormOut> {
    let (rows, w32) = rows_and_width("layernorm", x, width)?;
    // Without affine the kernel never reads w and b; x stands in for them.
    let (w, b) = affine.unwrap_or((x, x));
    if affine.is_some() {
        check_vector("layernorm weight", w, width)?;
        check_vector("layernorm bias", b, width)?;
    }
    let stats_shape = &x.shape()[..x.shape().len() - 1];
    let y = Tensor::empty(x.gpu(), x.shape(), DType::F32)?;
    let mean = Tensor::empty(x.gpu(), stats_shape, DType::F32)?;
    let rstd = Tensor::empty(x.gpu(), stats_shape, DType::F32)?;
    let shape = RowShape::of(x.gpu(), w32);
    let affine = affine.is_some() as u32;
    let p =
        Params { rows, width: w32, eps, rows_per_chunk: 0, affine, lanes: shape.lanes, residual: 0, _pad: 0 };
    rec.dispatch_linear(
        shape.pick(LAYERNORM_WG256_FORWARD, LAYERNORM_WG8_FORWARD),
        shape.groups(rows),
        args::LayernormWg256ForwardArgs { x, w, b, y: &y, mean: &mean, rstd: &rstd },
        &p,
    )?;
    Ok(LayerNormOut { y, mean, rstd })
}

/// Backward of [`layernorm`]: returns `dx` (plus `residual`, when given). With
/// `affine = Some((w, dw, db))` the weight enters `dx` and the parameter gradients are added
/// into `dw` and `db`.
#[allow(clippy::too_many_arguments)]
pub fn layernorm_backward(
    rec: &mut Recorder,
    x: &Tensor,
    width: usize,
    affine: Option<(&Tensor, &Tensor, &Tensor)>,
    mean: &Tensor,
    rstd: &Tensor,
    dy: &Tensor,
    residual: Option<&Tensor>,
) -> Result<Tensor> {
    let (rows, w32) = rows_and_width("layernorm backward", x, width)?;
    check_residual("layernorm backward", residual, x)?;
    check_vector("layernorm mean", mean, rows as usize)?;
    check_vector("layernorm rstd", rstd, rows as usize)?;
    if dy.shape() != x.shape() || dy.dtype() != DType::F32 {
        return Err(Error::Shape(format!("layernorm backward: dy {dy:?} must match x {x:?}")));
    }
    let w = match affine {
        Some((w, dw, db)) => {
            check_vector("layernorm weight", w, width)?;
            check_vector("layernorm weight gradient", dw, width)?;
            check_vector("layernorm bias gradient", db, width)?;
            w
        }
        None => x,
    };
    let dx = Tensor::empty(x.gpu(), x.shape(), DType::F32)?;
    let shape = RowShape::of(x.gpu(), w32);
    let mut p = Params {
        rows,
        width: w32,
        eps: 0.0,
        rows_per_chunk: 0,
        affine: affine.is_some() as u32,
        lanes: shape.lanes,
        residual: residual.is_some() as u32,
        _pad: 0,
    };
    // Without a residual, dy stands in for the binding the kernel then does not read.
    rec.dispatch_linear(
        shape.pick(LAYERNORM_WG256_BACKWARD, LAYERNORM_WG8_BACKWARD),
        shape.groups(rows),
        args::LayernormWg256BackwardArgs { x, w, mean, rstd, dy, dx: &dx, res: residual.unwrap_or(dy) },
        &p,
    )?;
    if let Some((_, dw, db)) = affine {
        let (per, chunks) = chunking(rows, x.gpu().caps().max_workgroup_count[1]);
        p.rows_per_chunk = per;
        let shape = [chunks as usize, width];
        let dw_part = Tensor::empty(x.gpu(), &shape, DType::F32)?;
        let db_part = Tensor::empty(x.gpu(), &shape, DType::F32)?;
        let args =
            args::LayernormWg256ParamGradsArgs { x, mean, rstd, dy, dw_part: &dw_part, db_part: &db_part };
        rec.dispatch(LAYERNORM_WG256_PARAM_GRADS, [w32.div_ceil(64), chunks, 1], args, &p)?;
        add_partials(rec, &dw_part, dw)?;
        add_partials(rec, &db_part, db)?;
    }
    Ok(dx)
}

/// Plain f64 loops.
pub mod reference {
    /// Returns (y, mean, rstd) for rows of `width`; `affine` is (w, b).
    pub fn layernorm(
        x: &[f64],
        width: usize,
        affine: Option<(&[f64], &[f64])>,
        eps: f64,
    ) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let (mut y, mut means, mut rstds) = (Vec::with_capacity(x.len()), Vec::new(), Vec::new());
        for row in x.chunks(width) {
            let mean = row.iter().sum::<f64>() / width as f64;
            let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / width as f64;
            let r = 1.0 / (var + eps).sqrt();
            for (j, v) in row.iter().enumerate() {
                let xhat = (v - mean) * r;
                y.push(match affine {
                    Some((w, b)) => xhat * w[j] + b[j],
                    None => xhat,
                });
            }
            means.push(mean);
            rstds.push(r);
        }
        (y, means, rstds)
    }

    /// Returns (dx, dw, db); dw and db are empty without affine.
    pub fn layernorm_backward(
        x: &[f64],
        width: usize,
        w: Option<&[f64]>,
        eps: f64,
        dy: &[f64],
    ) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let n = width as f64;
        let mut dx = Vec::with_capacity(x.len());
        let (mut dw, mut db) = (vec![0.0; width], vec![0.0; width]);
        for (row, gy) in x.chunks(width).zip(dy.chunks(width)) {
            let mean = row.iter().sum::<f64>() / n;
            let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n;
            let r = 1.0 / (var + eps).sqrt();
            let xhat: Vec<f64> = row.iter().map(|v| (v - mean) * r).collect();
            let g: Vec<f64> = (0..width).map(|j| gy[j] * w.map_or(1.0, |w| w[j])).collect();
            let mg = g.iter().sum::<f64>() / n;
            let mgx = g.iter().zip(&xhat).map(|(a, b)| a * b).sum::<f64>() / n;
            for j in 0..width {
                dx.push(r * (g[j] - mg - xhat[j] * mgx));
                dw[j] += gy[j] * xhat[j];
                db[j] += gy[j];
            }
        }
        if w.is_none() {
            dw.clear();
            db.clear();
        }
        (dx, dw, db)
    }
}
