//! Stable LSD radix sort of u32 keys with 32-bit values. Kernels: `shaders/sort.wgsl` (4-bit
//! digits) and `shaders/sort_bytes.wgsl` (8-bit digits, for GPUs).
//!
//! Sorts on the low `key_bits` bits of each key, a digit a pass from the least significant up,
//! so fewer key bits mean fewer passes (13 bits: 4 passes of 4 bits, the last on one bit, or 2
//! of 8). Each pass is a histogram per block of [`BLOCK`] elements, an exclusive scan of the
//! digit-major counts ([`crate::ops::scan`]) that gives every (digit, block) its place, and a
//! stable scatter; the passes ping-pong between two buffer pairs. [`Radix`] says which digits
//! and histograms a device takes. Every pass is stable, so the whole sort is: equal masked keys
//! keep their input order, and every way of sorting gives the same bits.
//!
//! Only the masked bits order the keys, but the keys come back whole, high bits included: a
//! caller that packs a payload above `key_bits` (the rasteriser packs tile and depth) gets it
//! back with its key, and one that wants masked keys can mask them.
//!
//! Tests: the harness's `sort` row (`engine/tests/ops/cases.rs`: forward against the f64 reference
//! at awkward shapes); `engine/tests/ops/scan_sort.rs` (stability, every key width, large inputs,
//! every [`Radix`] on one device).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::{
    SORT_BLOCK, SORT_BYTES_HISTOGRAM, SORT_BYTES_SCATTER, SORT_HISTOGRAM, SORT_HISTOGRAM_SUBGROUPS,
    SORT_SCATTER,
};
use crate::ops::scan::exclusive_scan;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// Bits sorted per pass of `shaders/sort.wgsl` (16 digits), which also sorts every input of one
/// block, whatever the [`Radix`].
pub const RADIX_BITS: u32 = 4;
/// Bits sorted per pass of `shaders/sort_bytes.wgsl` (256 digits).
pub const BYTE_BITS: u32 = 8;
/// Elements per workgroup; must match `BLOCK` in both shaders.
pub const BLOCK: usize = 4096;
/// The smallest and largest subgroups `shaders/sort_bytes.wgsl` ranks by: its per-subgroup
/// counters are sized for subgroups of at least 8, and a ballot holds 128 lanes.
const BYTE_SUBGROUPS: std::ops::RangeInclusive<u32> = 8..=128;

use crate::kernels::params::SortParams as Params;

/// Both 4-bit histogram kernels: one set of bindings and parameters.
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
    sort_with(rec, keys, Some(values), key_bits, Radix::Fastest)
}

/// How the passes of a sort of more than one block cut the keys and count their digits:
/// - 4-bit digits counted by workgroup atomics, one an element ([`Radix::Atomics`]);
/// - 4-bit digits counted by subgroup adds, one atomic a subgroup and digit
///   (`histogram_subgroups` in `shaders/sort.wgsl`: [`Radix::Subgroups`]);
/// - 8-bit digits, half the passes, counted and ranked by subgroup ballots
///   (`shaders/sort_bytes.wgsl`: [`Radix::Bytes`]).
///
/// [`Radix::Fastest`] takes 8-bit digits on a GPU whose subgroups can rank them (ballots, 8 to
/// 128 lanes), else 4-bit digits with subgroup histograms on a GPU that has subgroup
/// arithmetic; a CPU device keeps 4-bit digits and atomics, which cost it nothing more
/// (lavapipe, 262144 pairs of 32-bit keys: 28 ms with either histogram, within its noise;
/// docs/decisions/raster.md says why GPUs take the bytes). The tests run every one on one
/// device; `velox bench kernels` times every one the device can run.
#[doc(hidden)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Radix {
    Fastest,
    Atomics,
    Subgroups,
    Bytes,
}

impl Radix {
    /// Every way of sorting but [`Radix::Fastest`].
    pub const ALL: [Radix; 3] = [Radix::Atomics, Radix::Subgroups, Radix::Bytes];

    /// What [`Radix::Fastest`] takes on `gpu`.
    pub fn chosen(gpu: &crate::Gpu) -> Radix {
        if gpu.caps().cpu_kernels {
            Radix::Atomics
        } else if Radix::Bytes.runs_on(gpu) {
            Radix::Bytes
        } else if Radix::Subgroups.runs_on(gpu) {
            Radix::Subgroups
        } else {
            Radix::Atomics
        }
    }

    /// Whether `gpu` can sort this way.
    pub fn runs_on(self, gpu: &crate::Gpu) -> bool {
        self.check(gpu).is_ok()
    }

    /// Why `gpu` cannot sort this way, if it cannot.
    fn check(self, gpu: &crate::Gpu) -> Result<()> {
        match self {
            Radix::Fastest | Radix::Atomics => Ok(()),
            Radix::Subgroups => gpu.check_supported(SORT_HISTOGRAM_SUBGROUPS),
            Radix::Bytes => {
                gpu.check_supported(SORT_BYTES_HISTOGRAM)?;
                gpu.check_supported(SORT_BYTES_SCATTER)?;
                let c = gpu.caps();
                if BYTE_SUBGROUPS.contains(&c.min_subgroup_size)
                    && BYTE_SUBGROUPS.contains(&c.max_subgroup_size)
                {
                    Ok(())
                } else {
                    Err(Error::unsupported(
                        crate::error::Feature::SubgroupSize,
                        format!(
                            "8-bit radix digits need subgroups of 8 to 128 invocations; the device runs {}..={}",
                            c.min_subgroup_size, c.max_subgroup_size
                        ),
                    ))
                }
            }
        }
    }

    /// Bits a pass sorts (of a sort of more than one block).
    pub fn digit_bits(self, gpu: &crate::Gpu) -> u32 {
        match self {
            Radix::Fastest => Radix::chosen(gpu).digit_bits(gpu),
            Radix::Bytes => BYTE_BITS,
            Radix::Atomics | Radix::Subgroups => RADIX_BITS,
        }
    }

    pub fn describe(self) -> &'static str {
        match self {
            Radix::Fastest => "the device's fastest passes",
            Radix::Atomics => "4-bit digits, histograms by workgroup atomics",
            Radix::Subgroups => "4-bit digits, histograms by subgroup adds",
            Radix::Bytes => "8-bit digits, histograms and ranks by subgroup ballots",
        }
    }
}

/// [`sort_pairs`] a chosen way (for the tests and the benchmarks); an error where the device
/// cannot sort that way.
#[doc(hidden)]
pub fn sort_pairs_with(
    rec: &mut Recorder,
    keys: &Tensor,
    values: &Tensor,
    key_bits: u32,
    radix: Radix,
) -> Result<(Tensor, Tensor)> {
    radix.check(keys.gpu())?;
    sort_with(rec, keys, Some(values), key_bits, radix)
}

/// The keys sorted as [`sort_pairs`] sorts them, and the order that sorts them (each sorted
/// key's index in `keys`, u32): a sort of (key, index) pairs whose indices the kernels make
/// as they read the keys, with no pass to write them first.
pub fn sort_indices(rec: &mut Recorder, keys: &Tensor, key_bits: u32) -> Result<(Tensor, Tensor)> {
    sort_with(rec, keys, None, key_bits, Radix::Fastest)
}

/// [`sort_indices`] a chosen way (for the tests); an error where the device cannot sort that
/// way.
#[doc(hidden)]
pub fn sort_indices_with(
    rec: &mut Recorder,
    keys: &Tensor,
    key_bits: u32,
    radix: Radix,
) -> Result<(Tensor, Tensor)> {
    radix.check(keys.gpu())?;
    sort_with(rec, keys, None, key_bits, radix)
}

fn sort_with(
    rec: &mut Recorder,
    keys: &Tensor,
    values: Option<&Tensor>,
    key_bits: u32,
    radix: Radix,
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
        let tmp = if key_bits > RADIX_BITS { new_pair()? } else { out.clone() };
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
    let radix = if radix == Radix::Fastest { Radix::chosen(gpu) } else { radix };
    let digit_bits = radix.digit_bits(gpu);
    let digits = 1usize << digit_bits;
    let bytes = radix == Radix::Bytes;
    // The 4-bit passes' histogram kernel.
    let histogram: HistogramKernel =
        if radix == Radix::Subgroups { SORT_HISTOGRAM_SUBGROUPS } else { SORT_HISTOGRAM };
    let counts = Tensor::empty(gpu, &[digits * num_blocks], DType::U32)?;
    let offsets = Tensor::empty(gpu, &[digits * num_blocks], DType::U32)?;
    // A second pair is allocated only when there is a second pass.
    let mut src = (keys.clone(), values.clone());
    let mut shift = 0;
    while shift < key_bits {
        let bits = digit_bits.min(key_bits - shift);
        let params =
            Params { n, num_blocks: num_blocks as u32, shift, mask: (1u32 << bits) - 1, key_bits, iota };
        let blocks = num_blocks as u64;
        if bytes {
            let args = args::SortBytesHistogramArgs { keys_in: &src.0, counts: &counts };
            rec.dispatch_linear(SORT_BYTES_HISTOGRAM, blocks, args, &params)?;
        } else {
            let args = args::SortHistogramArgs { keys_in: &src.0, counts: &counts };
            rec.dispatch_linear(histogram, blocks, args, &params)?;
        }
        exclusive_scan(rec, &counts, &offsets)?;
        let (keys_in, values_in, keys_out, values_out) = (&src.0, &src.1, &out.0, &out.1);
        if bytes {
            let args =
                args::SortBytesScatterArgs { keys_in, values_in, offsets: &offsets, keys_out, values_out };
            rec.dispatch_linear(SORT_BYTES_SCATTER, blocks, args, &params)?;
        } else {
            let args = args::SortScatterArgs { keys_in, values_in, offsets: &offsets, keys_out, values_out };
            rec.dispatch_linear(SORT_SCATTER, blocks, args, &params)?;
        }
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

/// Number of passes of a sort of `n` elements on `key_bits` bits on `gpu`: one workgroup's
/// 4-bit passes for a single block, else the device's digits ([`Radix::chosen`]).
pub fn passes(gpu: &crate::Gpu, n: usize, key_bits: u32) -> u32 {
    let bits = if n <= BLOCK { RADIX_BITS } else { Radix::chosen(gpu).digit_bits(gpu) };
    key_bits.div_ceil(bits)
}

/// Bytes the sort of `n` pairs on `gpu` reads and writes in device memory (for GB/s in
/// benchmarks): per pass, the histogram reads the keys and the scatter reads and writes keys
/// and values (the scan of the counts is small beside them).
pub fn bytes_moved(gpu: &crate::Gpu, n: usize, key_bits: u32) -> u64 {
    passes(gpu, n, key_bits) as u64 * 5 * 4 * n as u64
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
