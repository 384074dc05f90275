//! The voxel decoder's head pre-activation, forward and backward, fused. Kernel:
//! `shaders/voxel_head.wgsl` (the formulas are in its header). Tests: the harness
//! (`engine/tests/ops/cases.rs`) and the voxel decoder's (`tests/models/voxel_decoder.rs`).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{VOXEL_HEAD_BACKWARD, VOXEL_HEAD_FORWARD};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::fit_u32;
use crate::kernels::params::VoxelHeadParams as Params;

/// Checks `features [cells, F]` (F = h, or 4 h with `directions`), `embedded [per, h]` and
/// `offsets [per, 3]`.
fn params(features: &Tensor, embedded: &Tensor, offsets: &Tensor, directions: bool) -> Result<Params> {
    let ok = |t: &Tensor| t.dtype() == DType::F32;
    let (per, h) = match embedded.shape() {
        &[per, h] if ok(embedded) => (per, h),
        _ => {
            return Err(Error::Shape(format!(
                "voxel head: the offsets' embedding must be f32 [per, h], got {embedded:?}"
            )))
        }
    };
    let f = if directions { 4 * h } else { h };
    let cells = match features.shape() {
        &[cells, w] if w == f && ok(features) => cells,
        _ => {
            return Err(Error::Shape(format!(
                "voxel head: features must be f32 [cells, {f}], got {features:?}"
            )))
        }
    };
    if offsets.shape() != [per, 3] || !ok(offsets) {
        return Err(Error::Shape(format!("voxel head: offsets must be f32 [{per}, 3], got {offsets:?}")));
    }
    let fit = |v: usize| fit_u32(v, || format!("voxel head of {cells} cells"));
    fit(cells * per * h)?;
    Ok(Params { cells: fit(cells)?, per: fit(per)?, h: fit(h)?, directions: directions as u32 })
}

/// `(pre, gelu(pre))`, each `[cells, per, h]`, in one pass.
pub fn forward(
    rec: &mut Recorder,
    features: &Tensor,
    embedded: &Tensor,
    offsets: &Tensor,
    directions: bool,
) -> Result<(Tensor, Tensor)> {
    let p = params(features, embedded, offsets, directions)?;
    let shape = [p.cells as usize, p.per as usize, p.h as usize];
    let pre = Tensor::empty(features.gpu(), &shape, DType::F32)?;
    let act = Tensor::empty(features.gpu(), &shape, DType::F32)?;
    let n = (p.cells * p.per * p.h) as u64;
    rec.dispatch_linear(
        VOXEL_HEAD_FORWARD,
        n.div_ceil(256),
        args::VoxelHeadForwardArgs { features, embedded, offsets, pre: &pre, act: &act },
        &p,
    )?;
    Ok((pre, act))
}

/// The features' gradient `[cells, F]` from `dpre [cells, per, h]`, in one pass.
pub fn backward(
    rec: &mut Recorder,
    features: &Tensor,
    embedded: &Tensor,
    offsets: &Tensor,
    directions: bool,
    dpre: &Tensor,
) -> Result<Tensor> {
    let p = params(features, embedded, offsets, directions)?;
    if dpre.dtype() != DType::F32 || dpre.shape() != [p.cells as usize, p.per as usize, p.h as usize] {
        return Err(Error::Shape(format!("voxel head backward: dpre {dpre:?} must be f32 [cells, per, h]")));
    }
    let d = Tensor::empty(features.gpu(), features.shape(), DType::F32)?;
    rec.dispatch_linear(
        VOXEL_HEAD_BACKWARD,
        (d.numel() as u64).div_ceil(256),
        args::VoxelHeadBackwardArgs { offsets, dpre, dfeatures: &d },
        &p,
    )?;
    Ok(d)
}

/// Plain f64 loops.
pub mod reference {
    /// `pre` for `features [cells, F]`, `embedded [per, h]`, `offsets [per, 3]`.
    pub fn pre(features: &[f64], embedded: &[f64], offsets: &[f64], h: usize, directions: bool) -> Vec<f64> {
        let per = embedded.len() / h;
        let f = if directions { 4 * h } else { h };
        let cells = features.len() / f;
        let mut out = Vec::with_capacity(cells * per * h);
        for c in 0..cells {
            for v in 0..per {
                for j in 0..h {
                    let mut x = features[c * f + j] + embedded[v * h + j];
                    if directions {
                        for k in 0..3 {
                            x += features[c * f + (k + 1) * h + j] * offsets[v * 3 + k];
                        }
                    }
                    out.push(x);
                }
            }
        }
        out
    }

    /// The gradient of `features [cells, F]` from `dpre [cells, per, h]`.
    pub fn pre_backward(offsets: &[f64], dpre: &[f64], cells: usize, h: usize, directions: bool) -> Vec<f64> {
        let per = offsets.len() / 3;
        let f = if directions { 4 * h } else { h };
        let mut out = vec![0.0; cells * f];
        for c in 0..cells {
            for v in 0..per {
                for j in 0..h {
                    let g = dpre[(c * per + v) * h + j];
                    out[c * f + j] += g;
                    if directions {
                        for k in 0..3 {
                            out[c * f + (k + 1) * h + j] += g * offsets[v * 3 + k];
                        }
                    }
                }
            }
        }
        out
    }
}
