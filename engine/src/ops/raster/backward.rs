//! The backward pass: per-pixel reverse blending into per-Gaussian image-space gradients, then
//! the projection backward per Gaussian. Kernels: `shaders/raster_backward.wgsl` (f32 atomic
//! add) or `raster_backward_cas.wgsl` (compare-and-swap, for devices without f32 atomics),
//! both reducing over the subgroup first; then `raster_project.wgsl`'s `project_backward`.

use super::forward::{BlendParams, ProjectParams};
use super::{Gaussians, Rendered};
use crate::error::{Error, Result};
use crate::kernels::{
    KernelId, RASTER_BACKWARD_CAS_MAIN, RASTER_BACKWARD_MAIN, RASTER_PROJECT_PROJECT_BACKWARD,
};
use crate::ops::fill::fill_bits;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};
use crate::Gpu;

/// Gradients of the loss with respect to the rasteriser's inputs (the module conventions:
/// log-scales, raw quaternions, opacity logits). Dropped Gaussians get zeros.
#[derive(Clone, Debug)]
pub struct Grads {
    pub means: Tensor,
    pub log_scales: Tensor,
    pub quats: Tensor,
    pub opacities: Tensor,
    pub colours: Tensor,
}

/// Which blend-backward kernel this device uses, or why it has none.
pub fn variant(gpu: &Gpu) -> Result<(KernelId, &'static str)> {
    if !gpu.caps().subgroup_arithmetic {
        return Err(Error::Unsupported(
            "the rasteriser's backward pass needs subgroup arithmetic and vote operations in compute shaders"
                .into(),
        ));
    }
    Ok(if gpu.supports(RASTER_BACKWARD_MAIN) {
        (RASTER_BACKWARD_MAIN, "subgroup add, then f32 atomic add")
    } else {
        (RASTER_BACKWARD_CAS_MAIN, "subgroup add, then compare-and-swap")
    })
}

/// Records the gradients of a loss given its gradients with respect to the image: `d_rgb`
/// `[H, W, 3]`, `d_alpha` and `d_depth` `[H, W]`. `g` must be the Gaussians `r` rendered.
pub fn render_backward(
    rec: &mut Recorder,
    g: &Gaussians,
    r: &Rendered,
    d_rgb: &Tensor,
    d_alpha: &Tensor,
    d_depth: &Tensor,
) -> Result<Grads> {
    let kernel = variant(rec.gpu())?.0;
    render_backward_with(rec, kernel, g, r, d_rgb, d_alpha, d_depth)
}

/// [`render_backward`] with the compare-and-swap kernel, to test the fallback on devices
/// that have f32 atomics.
pub fn render_backward_cas(
    rec: &mut Recorder,
    g: &Gaussians,
    r: &Rendered,
    d_rgb: &Tensor,
    d_alpha: &Tensor,
    d_depth: &Tensor,
) -> Result<Grads> {
    variant(rec.gpu())?;
    render_backward_with(rec, RASTER_BACKWARD_CAS_MAIN, g, r, d_rgb, d_alpha, d_depth)
}

fn render_backward_with(
    rec: &mut Recorder,
    kernel: KernelId,
    g: &Gaussians,
    r: &Rendered,
    d_rgb: &Tensor,
    d_alpha: &Tensor,
    d_depth: &Tensor,
) -> Result<Grads> {
    let n = g.check()?;
    let p = &r.projected;
    let img = &r.image;
    let cam = &p.camera;
    if n != p.n {
        return Err(Error::Shape(format!("render_backward: {n} Gaussians, but {} were rendered", p.n)));
    }
    let (h, w) = (cam.height as usize, cam.width as usize);
    for (t, shape, name) in
        [(d_rgb, vec![h, w, 3], "d_rgb"), (d_alpha, vec![h, w], "d_alpha"), (d_depth, vec![h, w], "d_depth")]
    {
        if t.dtype() != DType::F32 || t.shape() != shape.as_slice() {
            return Err(Error::Shape(format!("render_backward: {name} {t:?} must be f32 {shape:?}")));
        }
    }
    let gpu = rec.gpu().clone();
    let grad2d = Tensor::empty(&gpu, &[n, 10], DType::F32)?;
    fill_bits(rec, &grad2d, 0)?;
    let (tiles_x, tiles_y) = cam.tiles();
    rec.dispatch(
        kernel,
        [tiles_x, tiles_y, 1],
        &[&img.ranges, &img.ids, &p.proj, &img.final_t, &img.last, d_rgb, d_alpha, d_depth, &grad2d],
        &BlendParams::new(cam, img.background),
    )?;
    let grads = Grads {
        means: Tensor::empty(&gpu, &[n, 3], DType::F32)?,
        log_scales: Tensor::empty(&gpu, &[n, 3], DType::F32)?,
        quats: Tensor::empty(&gpu, &[n, 4], DType::F32)?,
        opacities: Tensor::empty(&gpu, &[n], DType::F32)?,
        colours: Tensor::empty(&gpu, &[n, 3], DType::F32)?,
    };
    rec.dispatch_linear(
        RASTER_PROJECT_PROJECT_BACKWARD,
        (n as u64).div_ceil(256),
        &[
            &g.means,
            &g.log_scales,
            &g.quats,
            &g.opacities,
            &g.colours,
            &p.counts,
            &grad2d,
            &grads.means,
            &grads.log_scales,
            &grads.quats,
            &grads.opacities,
            &grads.colours,
        ],
        &ProjectParams::new(cam, n),
    )?;
    Ok(grads)
}
