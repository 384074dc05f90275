//! Global L2 norm of a flat f32 buffer, for gradient clipping and logging. Kernel:
//! `shaders/norm.wgsl`.
//!
//! Two stages in one recording: up to [`max_groups`] workgroups per chunk write partial sums
//! of squares, then one workgroup adds them and writes `[norm, sum of squares]`. The result
//! stays on the device, where the AdamW kernel reads it ([`crate::ops::adamw`]); read it back
//! after the step for logging, and treat a non-finite norm as NaN or Inf in the gradients
//! ([`check_finite`]).
//!
//! Tests: the harness's `global_norm` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `tests/training/train_primitives.rs` (chunked, non-finite values).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{NORM_FINISH, NORM_SUMSQ_PARTIAL, VETO_MAIN};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// Workgroups of the first stage per chunk on a GPU: enough to fill a large one, few enough
/// that one workgroup adds the partials quickly.
pub const MAX_GROUPS: usize = 1024;
/// The same on a CPU device (lavapipe), where each workgroup's nine barriers cost a switch
/// between all its groups of SIMD lanes: a few per core do. The tiny config's gradient norm
/// took 8.3 ms there with 1024 (a profile of the demo), 0.47 ms with 16.
pub const MAX_GROUPS_CPU: usize = 16;

/// Workgroups of the first stage per chunk on `gpu`.
pub fn max_groups(gpu: &crate::Gpu) -> usize {
    if gpu.caps().cpu_kernels {
        MAX_GROUPS_CPU
    } else {
        MAX_GROUPS
    }
}

use crate::kernels::params::NormParams as Params;

/// Reusable device buffers of a norm: the partial sums and the `[norm, sum of squares]` result.
pub struct NormScratch {
    partials: Tensor,
    out: Tensor,
}

impl NormScratch {
    /// Scratch for norms of buffers of up to `numel` elements.
    pub fn new(gpu: &crate::Gpu, numel: usize) -> Result<NormScratch> {
        NormScratch::for_chunks(gpu, numel, chunk_len(gpu))
    }

    /// Scratch for [`global_norm_chunked`] with chunks of `chunk` elements.
    #[doc(hidden)]
    pub fn for_chunks(gpu: &crate::Gpu, numel: usize, chunk: usize) -> Result<NormScratch> {
        let partials =
            Tensor::empty(gpu, &[partials_needed(numel, chunk, max_groups(gpu)).max(1)], DType::F32)?;
        let out = Tensor::empty(gpu, &[2], DType::F32)?;
        Ok(NormScratch { partials, out })
    }

    /// The result: `[norm, sum of squares]`, f32, shape `[2]`.
    pub fn result(&self) -> &Tensor {
        &self.out
    }
}

/// The longest run of f32 elements one storage binding takes, a multiple of the view alignment
/// so that chunks of a flat buffer can be bound as views.
pub fn chunk_len(gpu: &crate::Gpu) -> usize {
    let caps = gpu.caps();
    let align = (caps.min_storage_buffer_offset_alignment.max(4) as usize).div_ceil(4);
    // Capped at 2^30 elements so every index in a kernel fits in u32 with room to spare.
    let max = ((caps.max_storage_buffer_range / 4) as usize).min(1 << 30);
    (max / align * align).max(align)
}

/// Partial sums the first stage writes for `n` elements in chunks of `chunk`.
fn partials_needed(n: usize, chunk: usize, max_groups: usize) -> usize {
    chunks(n, chunk).map(|(_, len)| groups_for(len, max_groups)).sum()
}

fn groups_for(len: usize, max_groups: usize) -> usize {
    len.div_ceil(256).min(max_groups)
}

/// Splits `n` elements into (start, len) runs of at most `chunk` elements.
pub(crate) fn chunks(n: usize, chunk: usize) -> impl Iterator<Item = (usize, usize)> {
    (0..n).step_by(chunk.max(1)).map(move |s| (s, chunk.min(n - s)))
}

/// Records the global norm of `x` (any shape, f32) and returns a new `[2]` tensor holding
/// `[norm, sum of squares]`. The norm of an empty tensor is 0.
pub fn global_norm(rec: &mut Recorder, x: &Tensor) -> Result<Tensor> {
    let scratch = NormScratch::new(x.gpu(), x.numel())?;
    global_norm_into(rec, x, &scratch)?;
    Ok(scratch.out)
}

/// As [`global_norm`], into `scratch` (made for at least `x.numel()` elements).
pub fn global_norm_into(rec: &mut Recorder, x: &Tensor, scratch: &NormScratch) -> Result<()> {
    global_norm_chunked(rec, x, scratch, chunk_len(x.gpu()))
}

/// As [`global_norm_into`] with a chosen chunk length (a multiple of the view alignment), so
/// that tests can cover the multi-chunk path on small buffers.
#[doc(hidden)]
pub fn global_norm_chunked(
    rec: &mut Recorder,
    x: &Tensor,
    scratch: &NormScratch,
    chunk: usize,
) -> Result<()> {
    if x.dtype() != DType::F32 {
        return Err(Error::Shape(format!("global norm needs f32, got {x:?}")));
    }
    if chunk == 0 || !chunk.is_multiple_of(x.view_alignment()) || chunk > chunk_len(x.gpu()) {
        return Err(Error::Invalid(format!(
            "global norm: chunk of {chunk} elements is not a positive multiple of the view alignment \
             {} within one binding",
            x.view_alignment()
        )));
    }
    let n = x.numel();
    let flat = x.reshape(&[n])?;
    let most = max_groups(x.gpu());
    let needed = partials_needed(n, chunk, most);
    if scratch.partials.numel() < needed || scratch.out.numel() < 2 {
        return Err(Error::Shape(format!(
            "global norm of {n} elements in chunks of {chunk} needs {needed} partials, the scratch has {}",
            scratch.partials.numel()
        )));
    }
    let mut base = 0usize;
    for (start, len) in chunks(n, chunk) {
        let part = flat.view(start, &[len])?;
        let groups = groups_for(len, most);
        let p = Params { n: len as u32, groups: groups as u32, partial_base: base as u32, count: 0 };
        rec.dispatch_linear(
            NORM_SUMSQ_PARTIAL,
            groups as u64,
            args::NormSumsqPartialArgs { x: &part, partials: &scratch.partials },
            &p,
        )?;
        base += groups;
    }
    let p = Params { n: 0, groups: 1, partial_base: 0, count: base as u32 };
    rec.dispatch(
        NORM_FINISH,
        [1, 1, 1],
        args::NormFinishArgs { partials: &scratch.partials, out: &scratch.out },
        &p,
    )
}

/// Records a veto of the step that reads `norm` (a `[norm, ...]` result of [`global_norm_into`],
/// written earlier in the recording): when `count[0]` (u32) exceeds `limit`, the norm becomes
/// +Inf, and the AdamW kernel, which skips its step on a non-finite norm, leaves the parameters
/// and moments as they were. For work sized ahead of a count the device makes in the same
/// recording (`shaders/veto.wgsl`); the host reads the count after the submission and runs the
/// step again with room enough. [`check_finite`] of a vetoed norm fails, as it does for an
/// overflow.
pub fn veto_if_over(rec: &mut Recorder, count: &Tensor, limit: u32, norm: &Tensor) -> Result<()> {
    if count.dtype() != DType::U32 || count.numel() == 0 {
        return Err(Error::Shape(format!("veto: the count {count:?} must be u32 with an element")));
    }
    if norm.dtype() != DType::F32 || norm.numel() == 0 {
        return Err(Error::Shape(format!("veto: the norm {norm:?} must be f32 with an element")));
    }
    let p = crate::kernels::params::VetoParams { limit, pad: 0 };
    rec.dispatch(VETO_MAIN, [1, 1, 1], args::VetoMainArgs { count, norm }, &p)
}

/// Reads a `[norm, sum of squares]` result back and fails with a clear message when the norm
/// is NaN or Inf, which means the gradients hold NaN or Inf (or squares past f32's range).
/// Returns the norm.
pub fn check_finite(result: &Tensor, what: &str) -> Result<f32> {
    check_finite_values(&result.read()?, what)
}

/// [`check_finite`] of a result already read back (a [`crate::Readback`]'s values).
pub fn check_finite_values(v: &[f32], what: &str) -> Result<f32> {
    let norm = v.first().copied().ok_or_else(|| Error::Shape(format!("{what}: empty norm result")))?;
    if !norm.is_finite() {
        return Err(Error::Invalid(format!(
            "{what}: the global norm is {norm}: they hold NaN or Inf (or values whose squares overflow \
             f32); an AdamW step given this norm left the parameters unchanged. Stop, and look at the \
             loss or lower the learning rate"
        )));
    }
    Ok(norm)
}

pub mod reference {
    /// sqrt(sum x^2) in f64.
    pub fn global_norm(x: &[f32]) -> f64 {
        x.iter().map(|&v| v as f64 * v as f64).sum::<f64>().sqrt()
    }
}
