//! View-dependent colour from spherical harmonics (degrees 1 to 3), as 3D Gaussian splatting's
//! PLY files carry it: the colour each Gaussian shows from a camera centre, for the rasteriser
//! to draw (`velox render` of another tool's scene). Kernel: `shaders/sh_colour.wgsl`; f64
//! reference: [`reference::sh_colour`](super::reference::sh_colour), which `velox view`'s
//! shader and `velox_io::ply` share. Tests: `engine/tests/ops/raster.rs`
//! (`spherical_harmonics_colour_each_gaussian_along_its_view`).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::params::ShColourParams as Params;
use crate::kernels::SH_COLOUR_MAIN;
use crate::ops::raster::Gaussians;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// Coefficients per colour channel of a Gaussian for SH degree `degree` (degree 0 excluded).
pub fn per_channel(degree: usize) -> usize {
    (degree + 1) * (degree + 1) - 1
}

/// The colours `[N, 3]` the Gaussians `g` show from the camera centre `eye`: their colours
/// (the degree-0 term) plus the harmonics `rest` `[N, 3K]` of degree `degree` (1 to 3; K =
/// [`per_channel`]) along the unit direction from `eye` to each mean. Not clamped: the
/// rasteriser clamps colours below at 0. A Gaussian whose mean is `eye` keeps its colour.
pub fn sh_colours(
    rec: &mut Recorder,
    g: &Gaussians,
    rest: &Tensor,
    degree: usize,
    eye: [f32; 3],
) -> Result<Tensor> {
    if !(1..=3).contains(&degree) {
        return Err(Error::Invalid(format!("spherical harmonics of degree {degree}: 1, 2 or 3 are drawn")));
    }
    if eye.iter().any(|v| !v.is_finite()) {
        return Err(Error::Invalid(format!("camera centre {eye:?} is not finite")));
    }
    let n = g.colours.shape().first().copied().unwrap_or(0);
    let k = per_channel(degree);
    for (what, t, width) in [("means", &g.means, 3), ("colours", &g.colours, 3), ("harmonics", rest, 3 * k)] {
        if t.dtype() != DType::F32 || t.shape() != [n, width] {
            return Err(Error::Shape(format!(
                "spherical harmonics of degree {degree}: {what} {t:?} must be f32 [{n}, {width}]"
            )));
        }
    }
    let colours = Tensor::empty(rec.gpu(), &[n, 3], DType::F32)?;
    if n == 0 {
        return Ok(colours);
    }
    let p = Params {
        n: fit_u32(n, || format!("{n} Gaussians"))?,
        degree: degree as u32,
        eye_x: eye[0],
        eye_y: eye[1],
        eye_z: eye[2],
    };
    let args = args::ShColourMainArgs { means: &g.means, base: &g.colours, rest, colours: &colours };
    rec.dispatch_linear(SH_COLOUR_MAIN, (n as u64).div_ceil(256), args, &p)?;
    Ok(colours)
}
