//! Concatenation of index lists. Kernel: `shaders/concat.wgsl`.
//!
//! A batched layout is built per sample (each sample's points, queries and windows numbered
//! from 0) and merged into the batch's numbering: [`copy_add`] copies a sample's list into its
//! place in the batch's list, adding the sample's first index.
//!
//! Tests: the harness's `concat` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/fill_copy.rs` (index concatenation).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::CONCAT_COPY_ADD;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

use crate::fit_u32;
use crate::kernels::params::ConcatParams as Params;

/// `dst[dst_start + i] = src[src_start + i] + add` for `i < count` (u32, wrapping).
pub fn copy_add(
    rec: &mut Recorder,
    src: &Tensor,
    src_start: usize,
    dst: &Tensor,
    dst_start: usize,
    count: usize,
    add: u32,
) -> Result<()> {
    if src.dtype() != DType::U32 || dst.dtype() != DType::U32 {
        return Err(Error::Shape(format!("copy_add needs u32 tensors, got {src:?} and {dst:?}")));
    }
    let fits = |start: usize, t: &Tensor| start.checked_add(count).is_some_and(|e| e <= t.numel());
    if !fits(src_start, src) || !fits(dst_start, dst) {
        return Err(Error::Shape(format!(
            "copy_add: {count} elements from {src_start} of {src:?} to {dst_start} of {dst:?} run past an end"
        )));
    }
    if count == 0 {
        return Ok(());
    }
    let fit = |v: usize| fit_u32(v, || format!("copy_add of {count} at {v}"));
    let p = Params { src_start: fit(src_start)?, dst_start: fit(dst_start)?, count: fit(count)?, add };
    fit(src_start + count)?;
    fit(dst_start + count)?;
    rec.dispatch_elements(CONCAT_COPY_ADD, count as u64, args::ConcatCopyAddArgs { src, dst }, &p)
}

pub mod reference {
    /// [`super::copy_add`] on the host, into a copy of `dst`.
    pub fn copy_add(
        src: &[u32],
        src_start: usize,
        dst: &[u32],
        dst_start: usize,
        count: usize,
        add: u32,
    ) -> Vec<u32> {
        let mut out = dst.to_vec();
        for i in 0..count {
            out[dst_start + i] = src[src_start + i].wrapping_add(add);
        }
        out
    }
}
