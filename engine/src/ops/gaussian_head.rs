//! The Gaussian decoder's head activations, forward and backward. Kernel:
//! `shaders/gaussian_head.wgsl` (the formulas are in its header). Tests: the harness
//! (`engine/tests/ops/cases.rs`) and `engine/tests/ops/elementwise.rs` (saturation).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::{GAUSSIAN_HEAD_BACKWARD, GAUSSIAN_HEAD_FORWARD};
use crate::ops::raster::Gaussians;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// Raw numbers per Gaussian: offset 3, scale 3, quaternion 4, opacity 1, rgb 3.
pub const RAW: usize = 14;

/// The activation's constants (docs/models.md: offset range 0.05, scales 0.001 to 0.01).
#[derive(Clone, Copy, Debug)]
pub struct HeadRange {
    pub offset_range: f32,
    pub scale_min: f32,
    pub scale_max: f32,
}

use crate::kernels::params::GaussianHeadParams as Params;

fn params(raw: &Tensor, centres: &Tensor, r: &HeadRange) -> Result<(usize, Params)> {
    let (m, v) = match (raw.shape(), centres.shape()) {
        (&[m, RAW], &[v, 3]) if v > 0 && m % v == 0 => (m, v),
        _ => {
            return Err(Error::Shape(format!(
                "gaussian head: raw must be [V * G, {RAW}] and centres [V, 3], got {raw:?} and {centres:?}"
            )))
        }
    };
    if !(r.scale_min > 0.0 && r.scale_max > r.scale_min && r.offset_range >= 0.0) {
        return Err(Error::Invalid(format!("gaussian head: bad ranges {r:?}")));
    }
    let fit = fit_u32(m, || format!("{m} Gaussians"))?;
    Ok((
        m,
        Params {
            gaussians: fit,
            per_voxel: (m / v) as u32,
            offset_range: r.offset_range,
            scale_min: r.scale_min,
            scale_max: r.scale_max,
        },
    ))
}

/// Maps the raw head output to the rasteriser's parameters of its M = V x G Gaussians.
pub fn head_forward(
    rec: &mut Recorder,
    raw: &Tensor,
    centres: &Tensor,
    range: &HeadRange,
) -> Result<Gaussians> {
    let (m, p) = params(raw, centres, range)?;
    let out = Gaussians::empty(raw.gpu(), m)?;
    let args = args::GaussianHeadForwardArgs {
        raw,
        centres,
        means: &out.means,
        log_scales: &out.log_scales,
        quats: &out.quats,
        logits: &out.opacities,
        colours: &out.colours,
    };
    rec.dispatch_linear(GAUSSIAN_HEAD_FORWARD, (m as u64).div_ceil(256), args, &p)?;
    Ok(out)
}

/// The gradient of the raw head output, given the gradients of the head's outputs.
pub fn head_backward(
    rec: &mut Recorder,
    raw: &Tensor,
    centres: &Tensor,
    range: &HeadRange,
    d: &Gaussians,
) -> Result<Tensor> {
    let (m, p) = params(raw, centres, range)?;
    let d_raw = Tensor::empty(raw.gpu(), &[m, RAW], DType::F32)?;
    let args = args::GaussianHeadBackwardArgs {
        raw,
        d_means: &d.means,
        d_log_scales: &d.log_scales,
        d_quats: &d.quats,
        d_logits: &d.opacities,
        d_colours: &d.colours,
        d_raw: &d_raw,
    };
    rec.dispatch_linear(GAUSSIAN_HEAD_BACKWARD, (m as u64).div_ceil(256), args, &p)?;
    Ok(d_raw)
}

pub mod reference {
    use super::{HeadRange, RAW};

    fn sigmoid(v: f64) -> f64 {
        1.0 / (1.0 + (-v).exp())
    }

    /// (means, log_scales, quats, logits, colours) of `raw` [M, 14] with `per_voxel` Gaussians
    /// per centre.
    #[allow(clippy::type_complexity)]
    pub fn head(raw: &[f64], centres: &[f64], per_voxel: usize, r: &HeadRange) -> [Vec<f64>; 5] {
        let mut out: [Vec<f64>; 5] = Default::default();
        for (m, g) in raw.chunks(RAW).enumerate() {
            let v = m / per_voxel;
            for a in 0..3 {
                out[0].push(centres[v * 3 + a] + (2.0 * sigmoid(g[a]) - 1.0) * r.offset_range as f64);
                let span = (r.scale_max - r.scale_min) as f64;
                out[1].push((r.scale_min as f64 + span * sigmoid(g[3 + a])).ln());
            }
            out[2].extend_from_slice(&g[6..10]);
            out[3].push(g[10]);
            for a in 0..3 {
                out[4].push(sigmoid(g[11 + a]));
            }
        }
        out
    }

    /// The gradient of `raw` [M, 14] from the gradients `d` of the head's five outputs (the
    /// order of [`head`]).
    pub fn head_backward(raw: &[f64], d: &[Vec<f64>; 5], r: &HeadRange) -> Vec<f64> {
        let ds = |v: f64| sigmoid(v) * (1.0 - sigmoid(v));
        let span = (r.scale_max - r.scale_min) as f64;
        let mut out = Vec::with_capacity(raw.len());
        for (m, g) in raw.chunks(RAW).enumerate() {
            for a in 0..3 {
                out.push(d[0][3 * m + a] * 2.0 * r.offset_range as f64 * ds(g[a]));
            }
            for a in 0..3 {
                let l = g[3 + a];
                out.push(d[1][3 * m + a] * span * ds(l) / (r.scale_min as f64 + span * sigmoid(l)));
            }
            out.extend_from_slice(&d[2][4 * m..4 * m + 4]);
            out.push(d[3][m]);
            for a in 0..3 {
                out.push(d[4][3 * m + a] * ds(g[11 + a]));
            }
        }
        out
    }
}
