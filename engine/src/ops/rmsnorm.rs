//! RMSNorm over the last axis with a learnable scale. Kernel: `shaders/rmsnorm.wgsl`.
//!
//! `y = x / sqrt(mean(x^2) + eps) * w`. The forward saves the per-row `rstd` for the backward,
//! which gives `dx` and adds `dw` into a gradient tensor.
//!
//! Tests: the harness's `rmsnorm` row (`engine/tests/ops/cases.rs`: forward and backward, the
//! reference against finite differences against the f64 reference at awkward shapes);
//! `tests/models/layers.rs` (stability at large, tiny and constant rows).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{
    RMSNORM_WG256_BACKWARD, RMSNORM_WG256_FORWARD, RMSNORM_WG256_PARAM_GRADS, RMSNORM_WG8_BACKWARD,
    RMSNORM_WG8_FORWARD,
};
use crate::ops::reduce::{reduce_into, Reduce};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::fit_u32;
use crate::kernels::params::RmsnormParams as Params;

/// Rows of `x` over its last axis, checked against the width of `w` (rows, width).
pub(crate) fn rows_and_width(what: &str, x: &Tensor, width: usize) -> Result<(u32, u32)> {
    if x.dtype() != DType::F32 || x.shape().last() != Some(&width) {
        return Err(Error::Shape(format!("{what}: x must be f32 with last axis {width}, got {x:?}")));
    }
    let rows = x.numel().checked_div(width).unwrap_or(0);
    let fit = |v: usize| fit_u32(v, || format!("{what} of {x:?}"));
    fit(x.numel())?;
    Ok((fit(rows)?, fit(width)?))
}

pub(crate) fn check_vector(what: &str, t: &Tensor, width: usize) -> Result<()> {
    if t.dtype() != DType::F32 || t.numel() != width {
        return Err(Error::Shape(format!("{what}: needs an f32 tensor of {width} elements, got {t:?}")));
    }
    Ok(())
}

/// How the row kernels (`shaders/include/row_reduce.wgsl`) run on a device. GPUs: workgroups
/// of 256 and a power of two of invocations per row giving each about 4 elements (narrow rows,
/// the widths of 32 to 128 of the small models, then share a workgroup instead of idling most
/// of it). CPU devices (`Caps::cpu_kernels`): the variant of workgroups of 8, one SIMD group on
/// lavapipe, with a row per invocation and no barrier; a barrier in a workgroup of 256 costs
/// a switch between its 32 SIMD groups there.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RowShape {
    pub cpu: bool,
    pub lanes: u32,
    pub wg: u32,
}

impl RowShape {
    pub(crate) fn of(gpu: &crate::Gpu, width: u32) -> RowShape {
        if gpu.caps().cpu_kernels {
            RowShape { cpu: true, lanes: 1, wg: 8 }
        } else {
            RowShape { cpu: false, lanes: width.div_ceil(4).next_power_of_two().clamp(1, 256), wg: 256 }
        }
    }

    /// Workgroups over `rows` rows.
    pub(crate) fn groups(&self, rows: u32) -> u64 {
        rows.div_ceil(self.wg / self.lanes) as u64
    }

    /// The variant of a row kernel this shape runs.
    pub(crate) fn pick<K>(&self, gpu_kernel: K, cpu_kernel: K) -> K {
        if self.cpu {
            cpu_kernel
        } else {
            gpu_kernel
        }
    }
}

/// Which variant the row kernels (softmax, RMSNorm, LayerNorm) run on this device, for `velox
/// info`.
pub fn row_variant(gpu: &crate::Gpu) -> &'static str {
    if gpu.caps().texel_kernels() {
        "a row per invocation in workgroups of 8 (one SIMD group), no barriers; softmax rows of a multiple of 4 as vec4s read through a texel buffer, in two passes (CPU kernels)"
    } else if gpu.caps().cpu_kernels {
        "a row per invocation in workgroups of 8 (one SIMD group), no barriers (CPU kernels)"
    } else {
        "workgroups of 256, a power of two of invocations per row, reductions in workgroup memory"
    }
}

/// Rows each invocation of a `param_grads` kernel sums: at least 256, and few enough chunks to
/// fit one dispatch dimension. Returns (rows per chunk, chunks).
pub(crate) fn chunking(rows: u32, max_groups: u32) -> (u32, u32) {
    let per = 256u32.max(rows.div_ceil(max_groups));
    (per, rows.div_ceil(per))
}

/// `grad += sum over axis 0 of partial [chunks, width]`.
pub(crate) fn add_partials(rec: &mut Recorder, partial: &Tensor, grad: &Tensor) -> Result<()> {
    reduce_into(rec, partial, 0, Reduce::Sum, grad, true)
}

/// Checks a residual gradient that a norm's backward adds into `dx` (like `x`).
pub(crate) fn check_residual(what: &str, residual: Option<&Tensor>, x: &Tensor) -> Result<()> {
    match residual {
        Some(r) if r.shape() != x.shape() || r.dtype() != DType::F32 => {
            Err(Error::Shape(format!("{what}: the residual gradient {r:?} must match x {x:?}")))
        }
        _ => Ok(()),
    }
}

/// RMSNorm of every row of `x` (last axis = `w.numel()`): returns `y` and the per-row `rstd`
/// (shape `x.shape()` without the last axis).
pub fn rmsnorm(rec: &mut Recorder, x: &Tensor, w: &Tensor, eps: f32) -> Result<(Tensor, Tensor)> {
    let width = w.numel();
    check_vector("rmsnorm weight", w, width)?;
    let (rows, width) = rows_and_width("rmsnorm", x, width)?;
    let y = Tensor::empty(x.gpu(), x.shape(), DType::F32)?;
    let rstd = Tensor::empty(x.gpu(), &x.shape()[..x.shape().len() - 1], DType::F32)?;
    let shape = RowShape::of(x.gpu(), width);
    let p = Params { rows, width, eps, rows_per_chunk: 0, lanes: shape.lanes, residual: 0 };
    rec.dispatch_linear(
        shape.pick(RMSNORM_WG256_FORWARD, RMSNORM_WG8_FORWARD),
        shape.groups(rows),
        args::RmsnormWg256ForwardArgs { x, w, y: &y, rstd: &rstd },
        &p,
    )?;
    Ok((y, rstd))
}

/// Backward of [`rmsnorm`]: returns `dx` (plus `residual`, when given: the gradient of a
/// pre-norm residual block's input in one pass) and, when `dw` is given, adds the weight
/// gradient into it (accumulation, so a weight used twice sums its gradients).
pub fn rmsnorm_backward(
    rec: &mut Recorder,
    x: &Tensor,
    w: &Tensor,
    rstd: &Tensor,
    dy: &Tensor,
    dw: Option<&Tensor>,
    residual: Option<&Tensor>,
) -> Result<Tensor> {
    let width = w.numel();
    check_vector("rmsnorm weight", w, width)?;
    let (rows, width) = rows_and_width("rmsnorm backward", x, width)?;
    check_vector("rmsnorm rstd", rstd, rows as usize)?;
    if dy.shape() != x.shape() || dy.dtype() != DType::F32 {
        return Err(Error::Shape(format!("rmsnorm backward: dy {dy:?} must match x {x:?}")));
    }
    check_residual("rmsnorm backward", residual, x)?;
    let dx = Tensor::empty(x.gpu(), x.shape(), DType::F32)?;
    let shape = RowShape::of(x.gpu(), width);
    let mut p = Params {
        rows,
        width,
        eps: 0.0,
        rows_per_chunk: 0,
        lanes: shape.lanes,
        residual: residual.is_some() as u32,
    };
    // Without a residual, dy stands in for the binding the kernel then does not read.
    let args = args::RmsnormWg256BackwardArgs { x, w, rstd, dy, dx: &dx, res: residual.unwrap_or(dy) };
    let kernel = shape.pick(RMSNORM_WG256_BACKWARD, RMSNORM_WG8_BACKWARD);
    rec.dispatch_linear(kernel, shape.groups(rows), args, &p)?;
    if let Some(dw) = dw {
        check_vector("rmsnorm weight gradient", dw, width as usize)?;
        let (per, chunks) = chunking(rows, x.gpu().caps().max_workgroup_count[1]);
        p.rows_per_chunk = per;
        let partial = Tensor::empty(x.gpu(), &[chunks as usize, width as usize], DType::F32)?;
        rec.dispatch(
            RMSNORM_WG256_PARAM_GRADS,
            [width.div_ceil(64), chunks, 1],
            args::RmsnormWg256ParamGradsArgs { x, rstd, dy, dw_part: &partial },
            &p,
        )?;
        add_partials(rec, &partial, dw)?;
    }
    Ok(dx)
}

/// Plain f64 loops.
pub mod reference {
    /// Returns (y, rstd) for rows of `w.len()`.
    pub fn rmsnorm(x: &[f64], w: &[f64], eps: f64) -> (Vec<f64>, Vec<f64>) {
        let n = w.len();
        let mut y = Vec::with_capacity(x.len());
        let mut rstd = Vec::new();
        for row in x.chunks(n) {
            let ms = row.iter().map(|v| v * v).sum::<f64>() / n as f64;
            let r = 1.0 / (ms + eps).sqrt();
            y.extend(row.iter().zip(w).map(|(v, wj)| v * r * wj));
            rstd.push(r);
        }
        (y, rstd)
    }

    /// Returns (dx, dw).
    pub fn rmsnorm_backward(x: &[f64], w: &[f64], eps: f64, dy: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let n = w.len();
        let (_, rstd) = rmsnorm(x, w, eps);
        let mut dx = Vec::with_capacity(x.len());
        let mut dw = vec![0.0; n];
        for ((row, g), r) in x.chunks(n).zip(dy.chunks(n)).zip(rstd) {
            // m = mean_j (dy_j w_j xhat_j)
            let m = (0..n).map(|j| g[j] * w[j] * row[j] * r).sum::<f64>() / n as f64;
            for j in 0..n {
                let xhat = row[j] * r;
                dx.push(r * (g[j] * w[j] - xhat * m));
                dw[j] += g[j] * xhat;
            }
        }
        (dx, dw)
    }
}
