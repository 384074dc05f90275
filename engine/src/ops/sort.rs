//! Stable LSD radix sort of u32 keys with 32-bit values. Kernels: `shaders/sort.wgsl`.
//!
//! Sorts on the low `key_bits` bits of each key, [`RADIX_BITS`] bits a pass from the least
//! significant digit up, so fewer key bits mean fewer passes (13 bits: 4 passes, the last on
//! one bit). Each pass is a histogram per block of [`BLOCK`] elements (its lanes' counts added
//! by subgroup on a GPU that can, by workgroup atomics elsewhere: [`Histogram`]), an exclusive
//! scan of the
//! digit-major counts ([`crate::ops::scan`]) that gives every (digit, block) its place, and a
//! stable scatter; the passes ping-pong between two buffer pairs. Every pass is stable, so the
//! whole sort is: equal masked keys keep their input order.
//!
//! Only the masked bits order the keys, but the keys come back whole, high bits included: a
//! caller that packs a payload above `key_bits` (the rasteriser packs tile and depth) gets it
//! back with its key, and one that wants masked keys can mask them.
//!
//! Tests: the harness's `sort` row (`engine/tests/ops/cases.rs`: forward against the f64 reference
//! at awkward shapes); `engine/tests/ops/scan_sort.rs` (stability, every key width, large inputs).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::{SORT_BLOCK, SORT_HISTOGRAM, SORT_HISTOGRAM_SUBGROUPS, SORT_SCATTER};
use crate::ops::scan::exclusive_scan;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// Bits sorted per pass (16 digits); the kernels count and rank 16 digits.
pub const RADIX_BITS: u32 = 4;
/// Elements per workgroup; must match `BLOCK` in `shaders/sort.wgsl`.
pub const BLOCK: usize = 4096;

use crate::kernels::params::SortParams as Params;

/// Both histogram kernels: one set of bindings and parameters.
type HistogramKernel = crate::kernels::Kernel<Params, args::SortHistogramArgs<'static>>;

/// Sorts `keys` (u32) with their `values` (u32, i32 or f32, moved as raw bits) by the low
/// `key_bits` bits of each key (1..=32), stably. Returns new tensors, shaped like the inputs,
/// holding the whole original keys and their values in sorted order; the inputs are untouched.
pub fn sort_pairs(
    rec: &mut Recorder,
    keys: &Tensor,
    values: &Tensor,
    key_bits: u32,
) -> Result<(Tensor, Tensor)> {
    sort_with(rec, keys, Some(values), key_bits, Histogram::Fastest)
}

/// How the passes count each block's digits: by workgroup atomics, one an element, or by
/// subgroup adds, one atomic a subgroup and digit (`histogram_subgroups` in
/// `shaders/sort.wgsl`). [`Histogram::Fastest`] takes subgroup adds on a GPU that has them,
/// where an element's atomic contends with the workgroup's for 16 counters; a CPU device keeps
/// the atomics, which cost it nothing more (lavapipe, 262144 pairs of 32-bit keys: 28 ms with
/// either, within its noise). The tests run both on one device; `velox bench kernels` times
/// both.
#[doc(hidden)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Histogram {
    Fastest,
    Atomics,
    Subgroups,
}

impl Histogram {
    /// What [`Histogram::Fastest`] takes on `gpu`: subgroup adds on a GPU that has them.
    pub fn chosen(gpu: &crate::Gpu) -> Histogram {
        if !gpu.caps().cpu_kernels && gpu.supports(SORT_HISTOGRAM_SUBGROUPS) {
            Histogram::Subgroups
        } else {
            Histogram::Atomics
        }
    }

    /// Whether `gpu` can count this way.
    pub fn runs_on(self, gpu: &crate::Gpu) -> bool {
        self.kernel(gpu).is_ok()
    }

    /// The histogram kernel this way of counting takes on `gpu`; an error where the device
    /// cannot run it.
    fn kernel(self, gpu: &crate::Gpu) -> Result<HistogramKernel> {
        match self {
            Histogram::Fastest => Histogram::chosen(gpu).kernel(gpu),
            Histogram::Atomics => Ok(SORT_HISTOGRAM),
            Histogram::Subgroups => {
                gpu.check_supported(SORT_HISTOGRAM_SUBGROUPS)?;
                Ok(SORT_HISTOGRAM_SUBGROUPS)
            }
        }
    }

    pub fn describe(self) -> &'static str {
        match self {
            Histogram::Fastest => "the device's fastest histograms",
            Histogram::Atomics => "histograms by workgroup atomics",
            Histogram::Subgroups => "histograms by subgroup adds",
        }
    }
}

/// [`sort_pairs`] with a chosen histogram kernel (for the tests and the benchmarks).
#[doc(hidden)]
pub fn sort_pairs_with(
    rec: &mut Recorder,
    keys: &Tensor,
    values: &Tensor,
    key_bits: u32,
    histogram: Histogram,
) -> Result<(Tensor, Tensor)> {
    sort_with(rec, keys, Some(values), key_bits, histogram)
}

/// The keys sorted as [`sort_pairs`] sorts them, and the order that sorts them (each sorted
/// key's index in `keys`, u32): a sort of (key, index) pairs whose indices the kernels make
/// as they read the keys, with no pass to write them first.
pub fn sort_indices(rec: &mut Recorder, keys: &Tensor, key_bits: u32) -> Result<(Tensor, Tensor)> {
    sort_with(rec, keys, None, key_bits, Histogram::Fastest)
}

fn sort_with(
    rec: &mut Recorder,
    keys: &Tensor,
    values: Option<&Tensor>,
    key_bits: u32,
    histogram: Histogram,
) -> Result<(Tensor, Tensor)> {
    let mut iota = values.is_none() as u32;
    // Without values the keys stand in for the bindings the kernels then do not read.
    let values = values.unwrap_or(keys);
    if keys.dtype() != DType::U32 {
        return Err(Error::DType(format!("sort_pairs: keys {keys:?} must be u32")));
    }
    if values.dtype().size() != 4 {
        return Err(Error::Shape(format!("sort_pairs: values {values:?} must be a 32-bit type")));
    }
    if keys.numel() != values.numel() {
        return Err(Error::Shape(format!(
            "sort_pairs: keys {keys:?} and values {values:?} differ in number of elements"
        )));
    }
    if !(1..=32).contains(&key_bits) {
        return Err(Error::Shape(format!("sort_pairs: key_bits is {key_bits}, it must be in 1..=32")));
    }
    let n = fit_u32(keys.numel(), || format!("sort_pairs: {keys:?} has 2^32 elements or more"))?;
    let gpu = keys.gpu();
    let value_type = if iota == 1 { DType::U32 } else { values.dtype() };
    let new_pair = || -> Result<(Tensor, Tensor)> {
        Ok((Tensor::empty(gpu, keys.shape(), DType::U32)?, Tensor::empty(gpu, values.shape(), value_type)?))
    };
    let mut out = new_pair()?;
    if n == 0 {
        return Ok(out);
    }

    let num_blocks = (n as usize).div_ceil(BLOCK);
    if num_blocks == 1 {
        // Every pass in one workgroup, one dispatch (`block` in the shader).
        let tmp = if passes(key_bits) > 1 { new_pair()? } else { out.clone() };
        let params = Params { n, num_blocks: 1, shift: 0, mask: 0, key_bits, iota };
        let args = args::SortBlockArgs {
            keys_in: keys,
            values_in: values,
            keys_out: &out.0,
            values_out: &out.1,
            keys_tmp: &tmp.0,
            values_tmp: &tmp.1,
        };
        rec.dispatch(SORT_BLOCK, [1, 1, 1], args, &params)?;
        return Ok(out);
    }
    let histogram = histogram.kernel(gpu)?;
    let counts = Tensor::empty(gpu, &[16 * num_blocks], DType::U32)?;
    let offsets = Tensor::empty(gpu, &[16 * num_blocks], DType::U32)?;
    // A second pair is allocated only when there is a second pass.
    let mut src = (keys.clone(), values.clone());
    let mut shift = 0;
    while shift < key_bits {
        let bits = RADIX_BITS.min(key_bits - shift);
        let params =
            Params { n, num_blocks: num_blocks as u32, shift, mask: (1u32 << bits) - 1, key_bits, iota };
        rec.dispatch_linear(
            histogram,
            num_blocks as u64,
            args::SortHistogramArgs { keys_in: &src.0, counts: &counts },
            &params,
        )?;
        exclusive_scan(rec, &counts, &offsets)?;
        rec.dispatch_linear(
            SORT_SCATTER,
            num_blocks as u64,
            args::SortScatterArgs {
                keys_in: &src.0,
                values_in: &src.1,
                offsets: &offsets,
                keys_out: &out.0,
                values_out: &out.1,
            },
            &params,
        )?;
        shift += bits;
        iota = 0;
        if shift < key_bits {
            // This pass's output is the next one's input, and this pass's input is free to be
            // the next output, unless it is the caller's.
            let next = if src.0.same_storage(keys) { new_pair()? } else { src.clone() };
            src = std::mem::replace(&mut out, next);
        }
    }
    Ok(out)
}

/// Number of passes for `key_bits` bits.
pub fn passes(key_bits: u32) -> u32 {
    key_bits.div_ceil(RADIX_BITS)
}

/// Bytes the sort of `n` pairs reads and writes in device memory (for GB/s in benchmarks):
/// per pass, the histogram reads the keys and the scatter reads and writes keys and values
/// (the scan of the counts is small beside them).
pub fn bytes_moved(n: usize, key_bits: u32) -> u64 {
    passes(key_bits) as u64 * 5 * 4 * n as u64
}

/// The CPU version the kernels are checked against.
pub mod reference {
    /// Stable sort of (key, value) pairs by `key & mask(key_bits)`; the keys come back whole.
    pub fn sort_pairs(keys: &[u32], values: &[u32], key_bits: u32) -> (Vec<u32>, Vec<u32>) {
        let mask = if key_bits >= 32 { u32::MAX } else { (1u32 << key_bits) - 1 };
        let mut pairs: Vec<(u32, u32)> = keys.iter().copied().zip(values.iter().copied()).collect();
        // `sort_by_key` is stable.
        pairs.sort_by_key(|&(k, _)| k & mask);
        pairs.into_iter().unzip()
    }
}
