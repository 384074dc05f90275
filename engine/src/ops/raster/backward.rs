//! The backward pass: per-pixel reverse blending into per-Gaussian image-space gradients, then
//! the projection backward per Gaussian. Three blend-backward kernels share one body
//! (`shaders/include/raster_backward_body.wgsl`), each reducing over the subgroup first:
//! - [`BackwardKernel::Ordered`] (`raster_backward.wgsl`, the default): per-pair gradients
//!   summed in a fixed order, so the same inputs give the same bits on every run; training
//!   uses it, which is what makes a run reproducible bit for bit;
//! - [`BackwardKernel::Atomic`] (`raster_backward_atomic.wgsl`): f32 atomic adds straight into
//!   each Gaussian's gradients, whose last bits depend on the order the GPU schedules them in;
//! - [`BackwardKernel::CompareAndSwap`] (`raster_backward_cas.wgsl`): the same with a
//!   compare-and-swap loop, for devices without f32 atomics.
//!
//! Then `raster_project.wgsl`'s `project_backward`.

use super::forward::{BlendParams, ProjectParams};
use super::{Gaussians, Rendered};
use crate::error::{Error, Feature, Result};
use crate::kernels::args;
use crate::kernels::{
    KernelId, RASTER_BACKWARD_ATOMIC_MAIN, RASTER_BACKWARD_CAS_MAIN, RASTER_BACKWARD_MAIN,
    RASTER_BACKWARD_SUM_PAIRS, RASTER_PROJECT_PROJECT_BACKWARD,
};
use crate::ops::fill::fill_bits;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};
use crate::Gpu;

/// The blend-backward kernels (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackwardKernel {
    /// Per-pair gradients summed in a fixed order: deterministic (the default).
    Ordered,
    /// f32 atomic adds: the sums' last bits vary between runs.
    Atomic,
    /// Compare-and-swap adds (no f32 atomics needed): the sums' last bits vary between runs.
    CompareAndSwap,
}

impl BackwardKernel {
    fn id(self) -> KernelId {
        match self {
            BackwardKernel::Ordered => RASTER_BACKWARD_MAIN.id(),
            BackwardKernel::Atomic => RASTER_BACKWARD_ATOMIC_MAIN.id(),
            BackwardKernel::CompareAndSwap => RASTER_BACKWARD_CAS_MAIN.id(),
        }
    }

    /// What the kernel does, for `velox info` and benchmark tables.
    pub fn describe(self) -> &'static str {
        match self {
            BackwardKernel::Ordered => "subgroup add, then per-pair sums in a fixed order (deterministic)",
            BackwardKernel::Atomic => "subgroup add, then f32 atomic add (order varies between runs)",
            BackwardKernel::CompareAndSwap => {
                "subgroup add, then compare-and-swap add (order varies between runs)"
            }
        }
    }

    /// Fails with the reason when `gpu` cannot run this kernel.
    pub fn check(self, gpu: &Gpu) -> Result<()> {
        if !gpu.caps().subgroup_arithmetic {
            return Err(Error::unsupported(
                Feature::Subgroups,
                "the rasteriser's backward pass needs subgroup arithmetic and vote operations in compute shaders",
            ));
        }
        gpu.check_supported(self.id())
    }

    /// The fast kernel of a device that has no need for reproducible bits (benchmarks): f32
    /// atomics where the device has them, else compare-and-swap.
    pub fn fastest(gpu: &Gpu) -> BackwardKernel {
        if gpu.supports(RASTER_BACKWARD_ATOMIC_MAIN) {
            BackwardKernel::Atomic
        } else {
            BackwardKernel::CompareAndSwap
        }
    }
}

/// The blend-backward kernel [`render_backward`] uses on this device (the deterministic one),
/// or why the device cannot run it.
pub fn variant(gpu: &Gpu) -> Result<(KernelId, &'static str)> {
    BackwardKernel::Ordered.check(gpu)?;
    Ok((BackwardKernel::Ordered.id(), BackwardKernel::Ordered.describe()))
}

/// Records the gradients of a loss given its gradients with respect to the image: `d_rgb`
/// `[H, W, 3]`, `d_alpha` and `d_depth` `[H, W]`. `g` must be the Gaussians `r` rendered. The
/// gradients are a set of the Gaussians' shapes (log-scales, raw quaternions, opacity logits);
/// dropped Gaussians get zeros. The result is deterministic ([`BackwardKernel::Ordered`]).
pub fn render_backward(
    rec: &mut Recorder,
    g: &Gaussians,
    r: &Rendered,
    d_rgb: &Tensor,
    d_alpha: &Tensor,
    d_depth: &Tensor,
) -> Result<Gaussians> {
    render_backward_with(rec, BackwardKernel::Ordered, g, r, d_rgb, d_alpha, d_depth)
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
) -> Result<Gaussians> {
    render_backward_with(rec, BackwardKernel::CompareAndSwap, g, r, d_rgb, d_alpha, d_depth)
}

/// [`render_backward`] with a chosen blend-backward kernel.
pub fn render_backward_with(
    rec: &mut Recorder,
    kernel: BackwardKernel,
    g: &Gaussians,
    r: &Rendered,
    d_rgb: &Tensor,
    d_alpha: &Tensor,
    d_depth: &Tensor,
) -> Result<Gaussians> {
    kernel.check(rec.gpu())?;
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
    let (tiles_x, tiles_y) = cam.tiles();
    let params = BlendParams::new(cam, img.background).for_backward(n as u32, img.room as u32);
    let (ranges, ids, proj, final_t, last_in) = (&img.ranges, &img.ids, &p.proj, &img.final_t, &img.last);
    if kernel == BackwardKernel::Ordered {
        let pairs = img.room;
        let pair_grads = Tensor::empty(&gpu, &[pairs, 10], DType::F32).map_err(|e| match e {
            Error::TooLarge { limit, what: why } => Error::too_large(limit, format!(
                "the deterministic rasteriser backward keeps 10 floats for each of {pairs} (tile, Gaussian) pairs: \
                 {why}; render at a lower resolution or with fewer or smaller Gaussians"
            )),
            other => other,
        })?;
        fill_bits(rec, &pair_grads, 0)?;
        let slots = &img.slots;
        let args = args::RasterBackwardMainArgs {
            ranges,
            ids,
            proj,
            final_t,
            last_in,
            d_rgb,
            d_alpha,
            d_depth,
            pair_grads: &pair_grads,
            slots,
        };
        rec.dispatch(RASTER_BACKWARD_MAIN, [tiles_x, tiles_y, 1], args, &params)?;
        rec.dispatch_linear(
            RASTER_BACKWARD_SUM_PAIRS,
            (n as u64).div_ceil(256),
            args::RasterBackwardSumPairsArgs {
                pair_grads: &pair_grads,
                counts: &p.counts,
                offsets: p.offsets(),
                grad2d: &grad2d,
            },
            &params,
        )?;
    } else {
        fill_bits(rec, &grad2d, 0)?;
        let args = args::RasterBackwardAtomicMainArgs {
            ranges,
            ids,
            proj,
            final_t,
            last_in,
            d_rgb,
            d_alpha,
            d_depth,
            grads: &grad2d,
        };
        let adds = if kernel == BackwardKernel::Atomic {
            RASTER_BACKWARD_ATOMIC_MAIN
        } else {
            RASTER_BACKWARD_CAS_MAIN
        };
        rec.dispatch(adds, [tiles_x, tiles_y, 1], args, &params)?;
    }
    let grads = Gaussians::empty(&gpu, n)?;
    rec.dispatch_linear(
        RASTER_PROJECT_PROJECT_BACKWARD,
        (n as u64).div_ceil(256),
        args::RasterProjectProjectBackwardArgs {
            means: &g.means,
            log_scales: &g.log_scales,
            quats: &g.quats,
            opacities: &g.opacities,
            colours: &g.colours,
            counts: &p.counts,
            grad2d: &grad2d,
            d_means: &grads.means,
            d_log_scales: &grads.log_scales,
            d_quats: &grads.quats,
            d_opacities: &grads.opacities,
            d_colours: &grads.colours,
        },
        &ProjectParams::new(cam, n),
    )?;
    Ok(grads)
}
