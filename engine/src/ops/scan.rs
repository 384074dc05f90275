//! Exclusive prefix scan of u32 with wrapping addition. Kernels: `shaders/scan.wgsl`.
//!
//! Multi-level: `block_scan` scans each block of 256 x `items` elements (256 invocations with
//! `items` consecutive elements each) in workgroup memory and writes the block totals to a
//! temporary; the host recurses on that temporary (each level is a block times shorter: with
//! the default [`ITEMS`], a million elements take two levels) and `add_block_offsets` adds
//! each block's scanned total back. The top level always has a single block, whose total is the
//! total of the whole input, so the op hands it back for free.
//!
//! Tests: the harness's `scan` row (`engine/tests/ops/cases.rs`: forward against the f64 reference
//! at awkward shapes); `engine/tests/ops/scan_sort.rs` (multi-level scans, many workgroups).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::{SCAN_ADD_BLOCK_OFFSETS, SCAN_BLOCK_SCAN};
use crate::ops::fill::fill_bits;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// Invocations per workgroup; must match `WG` in `shaders/scan.wgsl`.
pub const WG: usize = 256;
/// Elements per invocation that [`exclusive_scan`] uses: 16 made a million-element scan 8x
/// faster than 1 on lavapipe.
pub const ITEMS: u32 = 16;
/// The most elements per invocation [`exclusive_scan_items`] accepts (keeps the kernels'
/// 32-bit element indices from wrapping).
pub const MAX_ITEMS: u32 = 64;

use crate::kernels::params::ScanParams as Params;

/// Writes `output[i] = input[0] + ... + input[i-1]` (mod 2^32; `output[0] = 0`) and returns a
/// one-element u32 tensor holding the total of all of `input` (mod 2^32), which is ready when
/// the recording has been submitted.
///
/// `input` and `output` are u32 tensors with the same number of elements (any shapes) and must
/// not share storage.
pub fn exclusive_scan(rec: &mut Recorder, input: &Tensor, output: &Tensor) -> Result<Tensor> {
    exclusive_scan_items(rec, input, output, ITEMS)
}

/// [`exclusive_scan`] with `items` elements per invocation (1..=[`MAX_ITEMS`]), for benchmarks
/// and for tests that need many workgroups from a small tensor (`items = 1`).
pub fn exclusive_scan_items(
    rec: &mut Recorder,
    input: &Tensor,
    output: &Tensor,
    items: u32,
) -> Result<Tensor> {
    if !(1..=MAX_ITEMS).contains(&items) {
        return Err(Error::Shape(format!(
            "exclusive_scan: {items} items per invocation, it must be in 1..={MAX_ITEMS}"
        )));
    }
    if input.dtype() != DType::U32 || output.dtype() != DType::U32 {
        return Err(Error::Shape(format!("exclusive_scan takes u32 tensors, got {input:?} -> {output:?}")));
    }
    if input.numel() != output.numel() {
        return Err(Error::Shape(format!(
            "exclusive_scan: {input:?} and {output:?} differ in number of elements"
        )));
    }
    if input.same_storage(output) {
        return Err(Error::Shape("exclusive_scan: input and output must be different tensors".into()));
    }
    let n = fit_u32(input.numel(), || format!("exclusive_scan: {input:?} has 2^32 elements or more"))?;
    if n == 0 {
        let total = Tensor::empty(input.gpu(), &[1], DType::U32)?;
        fill_bits(rec, &total, 0)?;
        return Ok(total);
    }
    scan_level(rec, input, output, n, items)
}

/// One level: scan blocks, recurse on their totals, add the scanned totals back.
fn scan_level(rec: &mut Recorder, input: &Tensor, output: &Tensor, n: u32, items: u32) -> Result<Tensor> {
    let blocks = (n as usize).div_ceil(WG * items as usize);
    let params = Params { n, items };
    let sums = Tensor::empty(input.gpu(), &[blocks], DType::U32)?;
    rec.dispatch_linear(
        SCAN_BLOCK_SCAN,
        blocks as u64,
        args::ScanBlockScanArgs { src: input, dst: output, block_sums: &sums },
        &params,
    )?;
    if blocks == 1 {
        return Ok(sums);
    }
    let offsets = Tensor::empty(input.gpu(), &[blocks], DType::U32)?;
    let total = scan_level(rec, &sums, &offsets, blocks as u32, items)?;
    rec.dispatch_linear(
        SCAN_ADD_BLOCK_OFFSETS,
        blocks as u64,
        args::ScanAddBlockOffsetsArgs { dst: output, block_offsets: &offsets },
        &params,
    )?;
    Ok(total)
}

/// Bytes [`exclusive_scan`] of `n` elements reads and writes in device memory (for GB/s in
/// benchmarks): every level reads its input twice (caches may absorb the second read) and
/// writes its output, and below the top level reads and writes that output again.
pub fn bytes_moved(n: usize) -> u64 {
    let mut bytes = 0u64;
    let mut len = n;
    while len > 0 {
        let blocks = len.div_ceil(WG * ITEMS as usize);
        bytes += 4 * (3 * len + blocks) as u64;
        if blocks == 1 {
            break;
        }
        bytes += 4 * (2 * len + blocks) as u64;
        len = blocks;
    }
    bytes
}

/// The CPU version the kernels are checked against.
pub mod reference {
    /// Exclusive prefix sums with wrapping u32 addition, and the total.
    pub fn exclusive_scan(input: &[u32]) -> (Vec<u32>, u32) {
        let mut out = Vec::with_capacity(input.len());
        let mut sum = 0u32;
        for &x in input {
            out.push(sum);
            sum = sum.wrapping_add(x);
        }
        (out, sum)
    }
}
