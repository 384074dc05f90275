//! Fused multi-head attention over variable-length segments, forward and backward.
//! Kernels: `shaders/attention.wgsl` (one module per head width) and
//! `shaders/attention_blocks.wgsl` (the work lists).
//!
//! Rows are token-major, `[rows, heads, head_dim]`, and sorted by segment: segment `s` owns
//! query rows `q_offsets[s] .. q_offsets[s+1]` and key rows `k_offsets[s] .. k_offsets[s+1]`,
//! and its queries see only its keys. Dense self- or cross-attention is one segment; the
//! encoder's voxel-window self-attention and per-cell cross-attention are many. Empty segments
//! cost nothing; a query whose segment has no keys gets zeros.
//!
//! Tests: the harness's `attention` row (`engine/tests/ops/cases.rs`: forward and backward, the
//! reference against finite differences against the f64 reference at awkward shapes);
//! `engine/tests/ops/attention.rs` (f16 and cooperative kernels, long rows, segment layouts,
//! errors) and the layer's `tests/models/attention_layer.rs`.

use crate::error::{Error, Result};
use crate::kernels::{self, args, Kernel};
use crate::ops::fill::fill_bits;
use crate::ops::scan::exclusive_scan;
use crate::recorder::{Completion, Recorder};
use crate::tensor::{DType, Tensor};
use crate::Gpu;
use crate::{fit_u32, Feature, Limit};
use std::sync::{Arc, Mutex};

/// Rows per work item and per staged tile of the portable kernels (`B` in the shader).
pub const BLOCK: usize = 32;
/// Head widths with a compiled kernel.
pub const HEAD_DIMS: [usize; 4] = [16, 32, 64, 72];

/// Segment boundaries: two u32 tensors of `S + 1` offsets each.
///
/// The kernels walk work lists built from the offsets (blocks of rows, each in one segment;
/// four dispatches each). The layers of a model attend over the same segments many times, so
/// the lists are built once and kept here, shared by clones, for every later attention over
/// these segments in the same recording or after it has run.
#[derive(Clone, Debug)]
pub struct Segments {
    pub q_offsets: Tensor,
    pub k_offsets: Tensor,
    /// `Some(n)` when the keys of the segments are known to be exactly rows `0..n`, each in
    /// one segment: the backward pass then writes every row of dk and dv and needs no zeroed
    /// start.
    all_keys: Option<usize>,
    lists: Arc<Mutex<Vec<WorkList>>>,
}

/// A cached work list: over the query (`keys` false) or key offsets, in blocks of `block`
/// rows, recorded in the recording of `ready`.
#[derive(Clone, Debug)]
struct WorkList {
    keys: bool,
    block: usize,
    rows: usize,
    list: Tensor,
    capacity: usize,
    ready: Completion,
}

impl Segments {
    /// Segments from offsets on the device (u32 `[S + 1]` each, non-decreasing).
    pub fn new(q_offsets: Tensor, k_offsets: Tensor) -> Segments {
        Segments { q_offsets, k_offsets, all_keys: None, lists: Default::default() }
    }

    /// Segments whose keys are exactly rows `0..keys`, each in one segment (offsets that
    /// start at 0 and end at `keys`, as a grouping of every row gives).
    pub fn covering_keys(q_offsets: Tensor, k_offsets: Tensor, keys: usize) -> Segments {
        Segments { all_keys: Some(keys), ..Segments::new(q_offsets, k_offsets) }
    }

    /// One segment: every query sees every key.
    pub fn dense(gpu: &Gpu, nq: usize, nk: usize) -> Result<Segments> {
        Segments::from_lengths(gpu, &[nq], &[nk])
    }

    /// Segments of the given query and key lengths (equal counts; zeros allowed).
    pub fn from_lengths(gpu: &Gpu, q_lens: &[usize], k_lens: &[usize]) -> Result<Segments> {
        if q_lens.len() != k_lens.len() || q_lens.is_empty() {
            return Err(Error::Shape(format!(
                "segments need equal, non-zero numbers of query and key lengths, got {} and {}",
                q_lens.len(),
                k_lens.len()
            )));
        }
        let offsets = |lens: &[usize]| -> Result<Vec<u32>> {
            let mut acc = 0usize;
            let mut out = vec![0u32];
            for &l in lens {
                acc += l;
                out.push(fit_u32(acc, || "segment offsets".into())?);
            }
            Ok(out)
        };
        let (qo, ko) = (offsets(q_lens)?, offsets(k_lens)?);
        let keys = *ko.last().expect("one offset at least") as usize;
        Ok(Segments::covering_keys(
            Tensor::from_slice(gpu, &[qo.len()], &qo)?,
            Tensor::from_slice(gpu, &[ko.len()], &ko)?,
            keys,
        ))
    }

    /// The work list over the query or key rows in blocks of `block`, from the cache when it
    /// holds one that `rec` may read.
    fn work_list(
        &self,
        rec: &mut Recorder,
        keys: bool,
        rows: usize,
        block: usize,
    ) -> Result<(Tensor, usize)> {
        let mut lists = self.lists.lock().unwrap();
        let now = rec.completion().clone();
        if let Some(w) = lists
            .iter()
            .find(|w| w.keys == keys && w.block == block && w.rows == rows && w.ready.visible_in(&now))
        {
            return Ok((w.list.clone(), w.capacity));
        }
        let offsets = if keys { &self.k_offsets } else { &self.q_offsets };
        let (list, capacity) = work_list(rec, offsets, rows, block)?;
        // A list of a recording that never ran is of no use: replace it.
        lists.retain(|w| !(w.keys == keys && w.block == block && w.rows == rows));
        lists.push(WorkList { keys, block, rows, list: list.clone(), capacity, ready: now });
        Ok((list, capacity))
    }

    pub fn count(&self) -> usize {
        self.q_offsets.numel().saturating_sub(1)
    }
}

/// The forward pass's outputs: `o [Nq, H, D]` and the row log-sum-exp `lse [Nq, H]`, which
/// the backward pass needs.
#[derive(Clone, Debug)]
pub struct AttentionOut {
    pub o: Tensor,
    pub lse: Tensor,
}

#[derive(Clone, Debug)]
pub struct AttentionGrads {
    pub dq: Tensor,
    pub dk: Tensor,
    pub dv: Tensor,
}

use crate::kernels::params::AttentionCommonParams as Params;

use crate::kernels::params::AttentionBlocksParams as BlockParams;

// The attention kernels of every head size and precision share one declaration of their push
// constants and, per pass, one list of buffers.
type ForwardKernel = Kernel<Params, args::AttentionD16FwdArgs<'static>>;
type DqKernel = Kernel<Params, args::AttentionD16BwdDqArgs<'static>>;
type DkvKernel = Kernel<Params, args::AttentionD16BwdDkvArgs<'static>>;

struct Kernels {
    fwd: ForwardKernel,
    /// The forward pass on f16 q, k, v.
    fwd_f16: ForwardKernel,
    /// The same on cooperative matrices, 16x16x16 and 8x8x8 fragments, each in blocks of
    /// [`COOP_BLOCKS_16`] and [`COOP_BLOCKS_8`] query rows (the first index) and tiles of
    /// [`COOP_KEY_TILES`] keys (the second).
    fwd_coop16: [[ForwardKernel; 2]; 2],
    fwd_coop8: [[ForwardKernel; 2]; 2],
    dq: DqKernel,
    dkv: DkvKernel,
    /// The backward pass on cooperative matrices, 16x16x16 and 8x8x8 fragments: (dq, dkv).
    bwd_coop16: (DqKernel, DkvKernel),
    bwd_coop8: (DqKernel, DkvKernel),
    /// The backward pass on f16 q, k, v (everything else f32).
    dq_f16: DqKernel,
    dkv_f16: DkvKernel,
    /// The kernels for CPU devices (`attention_cpu.wgsl`, `attention_cpu_f16.wgsl`), in blocks
    /// of [`CPU_BLOCK`] rows: the forward pass and the two backward ones, on f32 and on f16.
    cpu: CpuKernels,
    cpu_f16: CpuKernels,
}

#[derive(Clone, Copy)]
struct CpuKernels {
    fwd: ForwardKernel,
    dq: DqKernel,
    dkv: DkvKernel,
}

fn kernels_for(d: usize) -> Option<Kernels> {
    use kernels::*;
    Some(match d {
        16 => Kernels {
            fwd: ATTENTION_D16_FWD,
            fwd_f16: ATTENTION_F16_D16_FWD,
            fwd_coop16: [
                [ATTENTION_COOP_D16_BQ32_BK32_FWD, ATTENTION_COOP_D16_BQ32_BK64_FWD],
                [ATTENTION_COOP_D16_BQ128_BK32_FWD, ATTENTION_COOP_D16_BQ128_BK64_FWD],
            ],
            fwd_coop8: [
                [ATTENTION_COOP8_D16_BQ32_BK32_FWD, ATTENTION_COOP8_D16_BQ32_BK64_FWD],
                [ATTENTION_COOP8_D16_BQ64_BK32_FWD, ATTENTION_COOP8_D16_BQ64_BK64_FWD],
            ],
            dq: ATTENTION_D16_BWD_DQ,
            dkv: ATTENTION_D16_BWD_DKV,
            bwd_coop16: (ATTENTION_COOP_BWD_D16_DQ_COOP, ATTENTION_COOP_BWD_D16_DKV_COOP),
            bwd_coop8: (ATTENTION_COOP8_BWD_D16_DQ_COOP, ATTENTION_COOP8_BWD_D16_DKV_COOP),
            dq_f16: ATTENTION_F16_D16_BWD_DQ,
            dkv_f16: ATTENTION_F16_D16_BWD_DKV,
            cpu: CpuKernels {
                fwd: ATTENTION_CPU_D16_FWD,
                dq: ATTENTION_CPU_D16_BWD_DQ,
                dkv: ATTENTION_CPU_D16_BWD_DKV,
            },
            cpu_f16: CpuKernels {
                fwd: ATTENTION_CPU_F16_D16_FWD,
                dq: ATTENTION_CPU_F16_D16_BWD_DQ,
                dkv: ATTENTION_CPU_F16_D16_BWD_DKV,
            },
        },
        32 => Kernels {
            fwd: ATTENTION_D32_FWD,
            fwd_f16: ATTENTION_F16_D32_FWD,
            fwd_coop16: [
                [ATTENTION_COOP_D32_BQ32_BK32_FWD, ATTENTION_COOP_D32_BQ32_BK64_FWD],
                [ATTENTION_COOP_D32_BQ128_BK32_FWD, ATTENTION_COOP_D32_BQ128_BK64_FWD],
            ],
            fwd_coop8: [
                [ATTENTION_COOP8_D32_BQ32_BK32_FWD, ATTENTION_COOP8_D32_BQ32_BK64_FWD],
                [ATTENTION_COOP8_D32_BQ64_BK32_FWD, ATTENTION_COOP8_D32_BQ64_BK64_FWD],
            ],
            dq: ATTENTION_D32_BWD_DQ,
            dkv: ATTENTION_D32_BWD_DKV,
            bwd_coop16: (ATTENTION_COOP_BWD_D32_DQ_COOP, ATTENTION_COOP_BWD_D32_DKV_COOP),
            bwd_coop8: (ATTENTION_COOP8_BWD_D32_DQ_COOP, ATTENTION_COOP8_BWD_D32_DKV_COOP),
            dq_f16: ATTENTION_F16_D32_BWD_DQ,
            dkv_f16: ATTENTION_F16_D32_BWD_DKV,
            cpu: CpuKernels {
                fwd: ATTENTION_CPU_D32_FWD,
                dq: ATTENTION_CPU_D32_BWD_DQ,
                dkv: ATTENTION_CPU_D32_BWD_DKV,
            },
            cpu_f16: CpuKernels {
                fwd: ATTENTION_CPU_F16_D32_FWD,
                dq: ATTENTION_CPU_F16_D32_BWD_DQ,
                dkv: ATTENTION_CPU_F16_D32_BWD_DKV,
            },
        },
        64 => Kernels {
            fwd: ATTENTION_D64_FWD,
            fwd_f16: ATTENTION_F16_D64_FWD,
            fwd_coop16: [
                [ATTENTION_COOP_D64_BQ32_BK32_FWD, ATTENTION_COOP_D64_BQ32_BK64_FWD],
                [ATTENTION_COOP_D64_BQ128_BK32_FWD, ATTENTION_COOP_D64_BQ128_BK64_FWD],
            ],
            fwd_coop8: [
                [ATTENTION_COOP8_D64_BQ32_BK32_FWD, ATTENTION_COOP8_D64_BQ32_BK64_FWD],
                [ATTENTION_COOP8_D64_BQ64_BK32_FWD, ATTENTION_COOP8_D64_BQ64_BK64_FWD],
            ],
            dq: ATTENTION_D64_BWD_DQ,
            dkv: ATTENTION_D64_BWD_DKV,
            bwd_coop16: (ATTENTION_COOP_BWD_D64_DQ_COOP, ATTENTION_COOP_BWD_D64_DKV_COOP),
            bwd_coop8: (ATTENTION_COOP8_BWD_D64_DQ_COOP, ATTENTION_COOP8_BWD_D64_DKV_COOP),
            dq_f16: ATTENTION_F16_D64_BWD_DQ,
            dkv_f16: ATTENTION_F16_D64_BWD_DKV,
            cpu: CpuKernels {
                fwd: ATTENTION_CPU_D64_FWD,
                dq: ATTENTION_CPU_D64_BWD_DQ,
                dkv: ATTENTION_CPU_D64_BWD_DKV,
            },
            cpu_f16: CpuKernels {
                fwd: ATTENTION_CPU_F16_D64_FWD,
                dq: ATTENTION_CPU_F16_D64_BWD_DQ,
                dkv: ATTENTION_CPU_F16_D64_BWD_DKV,
            },
        },
        72 => Kernels {
            fwd: ATTENTION_D72_FWD,
            fwd_f16: ATTENTION_F16_D72_FWD,
            fwd_coop16: [
                [ATTENTION_COOP_D72_BQ32_BK32_FWD, ATTENTION_COOP_D72_BQ32_BK64_FWD],
                [ATTENTION_COOP_D72_BQ128_BK32_FWD, ATTENTION_COOP_D72_BQ128_BK64_FWD],
            ],
            fwd_coop8: [
                [ATTENTION_COOP8_D72_BQ32_BK32_FWD, ATTENTION_COOP8_D72_BQ32_BK64_FWD],
                [ATTENTION_COOP8_D72_BQ64_BK32_FWD, ATTENTION_COOP8_D72_BQ64_BK64_FWD],
            ],
            dq: ATTENTION_D72_BWD_DQ,
            dkv: ATTENTION_D72_BWD_DKV,
            bwd_coop16: (ATTENTION_COOP_BWD_D72_DQ_COOP, ATTENTION_COOP_BWD_D72_DKV_COOP),
            bwd_coop8: (ATTENTION_COOP8_BWD_D72_DQ_COOP, ATTENTION_COOP8_BWD_D72_DKV_COOP),
            dq_f16: ATTENTION_F16_D72_BWD_DQ,
            dkv_f16: ATTENTION_F16_D72_BWD_DKV,
            cpu: CpuKernels {
                fwd: ATTENTION_CPU_D72_FWD,
                dq: ATTENTION_CPU_D72_BWD_DQ,
                dkv: ATTENTION_CPU_D72_BWD_DKV,
            },
            cpu_f16: CpuKernels {
                fwd: ATTENTION_CPU_F16_D72_FWD,
                dq: ATTENTION_CPU_F16_D72_BWD_DQ,
                dkv: ATTENTION_CPU_F16_D72_BWD_DKV,
            },
        },
        _ => return None,
    })
}

/// Rows per work item of the CPU kernels: one SIMD group of 8 lanes, a row each.
pub const CPU_BLOCK: usize = 8;

/// The CPU kernels for head width `d` and q's dtype, where this device takes them: a CPU device
/// (`Caps::cpu_kernels`) whose subgroups are exactly the kernels' workgroup of 8 lanes (their
/// shuffles read the other lanes; on wider SIMD groups lanes would idle, and lavapipe at 16 or
/// 32 lanes compiles them for minutes), and that can make all three.
fn cpu_kernels(gpu: &Gpu, d: usize, dtype: DType) -> Option<CpuKernels> {
    let caps = gpu.caps();
    let one_simd_group =
        caps.min_subgroup_size == CPU_BLOCK as u32 && caps.max_subgroup_size == CPU_BLOCK as u32;
    if !caps.cpu_kernels || !one_simd_group {
        return None;
    }
    let kern = kernels_for(d)?;
    let k = if dtype == DType::F16 { kern.cpu_f16 } else { kern.cpu };
    (gpu.supports(k.fwd) && gpu.supports(k.dq) && gpu.supports(k.dkv)).then_some(k)
}

/// Which attention kernels inputs of head width `d` and `dtype` run on this device when no
/// cooperative-matrix kernel takes them, for `velox info` and the benchmarks.
pub fn portable_variant(gpu: &Gpu, d: usize, dtype: DType) -> &'static str {
    if cpu_kernels(gpu, d, dtype).is_some() {
        "CPU: a SIMD group of 8 rows, keys shared by subgroup shuffles, no workgroup memory"
    } else {
        "portable: a row per invocation, keys staged in workgroup memory"
    }
}

/// Shapes (nq, nk, heads, head_dim) after checking q, k, v and the segments.
fn check(q: &Tensor, k: &Tensor, v: &Tensor, seg: &Segments) -> Result<(usize, usize, usize, usize)> {
    let (&[nq, h, d], &[nk, hk, dk]) = (q.shape(), k.shape()) else {
        return Err(Error::Shape(format!("attention needs q [Nq, H, D] and k [Nk, H, D], got {q:?}, {k:?}")));
    };
    if (hk, dk) != (h, d) || v.shape() != k.shape() {
        return Err(Error::Shape(format!(
            "attention: q {q:?}, k {k:?} and v {v:?} disagree on heads or width"
        )));
    }
    if [k, v].iter().any(|t| t.dtype() != q.dtype()) || !matches!(q.dtype(), DType::F32 | DType::F16) {
        return Err(Error::DType(format!(
            "attention needs q, k, v all f32 or all f16, got {q:?}, {k:?}, {v:?}"
        )));
    }
    if kernels_for(d).is_none() {
        return Err(Error::unsupported(
            Feature::KernelVariant,
            format!("attention head width {d}: compiled widths are {HEAD_DIMS:?}"),
        ));
    }
    let (qo, ko) = (&seg.q_offsets, &seg.k_offsets);
    if qo.dtype() != DType::U32 || ko.dtype() != DType::U32 || qo.shape() != ko.shape() || qo.numel() < 2 {
        return Err(Error::Shape(format!(
            "segment offsets must be two u32 tensors of S + 1 >= 2 entries, got {qo:?} and {ko:?}"
        )));
    }
    for t in [q, k] {
        if u32::try_from(t.numel()).is_err() {
            return Err(Error::too_large(Limit::Index, format!("attention on {t:?}")));
        }
    }
    Ok((nq, nk, h, d))
}

/// Query rows per block of the cooperative-matrix forward kernels, by fragment size: 16x16x16
/// fragments (NVIDIA) and 8x8x8 (lavapipe from Mesa 26, whose 32 KiB of workgroup memory hold
/// blocks of 64). Each block has one subgroup per F rows. Short segments (the encoder's
/// 32-token windows) take the short blocks; long ones the tall blocks, which read each staged
/// key and value tile for more rows.
pub const COOP_BLOCKS_16: [usize; 2] = [32, 128];
pub const COOP_BLOCKS_8: [usize; 2] = [32, 64];

/// Keys per staged tile of the cooperative-matrix forward kernels: 64 halves the barriers and
/// the softmax's votes per key where segments are long enough to fill the tiles, and the
/// workgroup memory holds them (see `attention_coop.wgsl`).
pub const COOP_KEY_TILES: [usize; 2] = [32, 64];

/// A cooperative-matrix forward kernel, with its block of query rows and tile of keys.
#[derive(Clone, Copy, Debug)]
pub struct CoopForward {
    pub kernel: ForwardKernel,
    pub rows: usize,
    pub keys: usize,
}

/// The cooperative-matrix forward kernel for f16 inputs of head width `d` on this device, in
/// `tall` or short blocks of query rows (see [`COOP_BLOCKS_16`] and [`COOP_BLOCKS_8`]) and tiles
/// of 64 keys where `long_keys` asks for them, if the device has it: FxFxF f16 fragments with
/// F = 16 or 8 (see `Caps::coop_matrix_f16`), subgroups of exactly F*F/8 invocations (each query
/// row belongs to F/8 lanes of one subgroup), subgroup shuffles and votes, and the kernel's
/// workgroup memory. What does not fit in workgroup memory gives way: the wide key tile first
/// (a tall block reads each key for four times the rows, which outweighs half the barriers),
/// then the tall block.
pub fn coop_forward_kernel(gpu: &Gpu, d: usize, tall: bool, long_keys: bool) -> Option<CoopForward> {
    let kern = kernels_for(d)?;
    // The forward pass also votes (subgroupAny) on moving the running maxima.
    let (kernels, blocks) = match coop_fragment(gpu).filter(|_| gpu.caps().subgroup_arithmetic)? {
        16 => (kern.fwd_coop16, COOP_BLOCKS_16),
        _ => (kern.fwd_coop8, COOP_BLOCKS_8),
    };
    let rows: &[usize] = if tall { &[1, 0] } else { &[0] };
    let keys: &[usize] = if long_keys { &[1, 0] } else { &[0] };
    rows.iter()
        .flat_map(|&r| keys.iter().map(move |&k| (r, k)))
        .map(|(r, k)| CoopForward { kernel: kernels[r][k], rows: blocks[r], keys: COOP_KEY_TILES[k] })
        .find(|c| gpu.supports(c.kernel))
}

/// Rows per work item of the cooperative-matrix backward kernels, on either side: query rows
/// for dq, key rows for dk and dv (`BQ` in `attention_coop_bwd.wgsl`).
pub const COOP_BWD_BLOCK: usize = 32;

/// The cooperative-matrix backward kernels (dq, then dk and dv) for f16 inputs of head width
/// `d` on this device, if it has them: the forward kernels' conditions (F = 16 or 8, subgroups
/// of F*F/8 invocations, shuffles, not a CPU device's kernels), and the kernels' workgroup
/// memory.
fn coop_backward_kernels(gpu: &Gpu, d: usize) -> Option<(DqKernel, DkvKernel)> {
    let kern = kernels_for(d)?;
    let kernels = match coop_fragment(gpu)? {
        16 => kern.bwd_coop16,
        _ => kern.bwd_coop8,
    };
    (gpu.supports(kernels.0) && gpu.supports(kernels.1)).then_some(kernels)
}

/// The fragment size F (16 or 8) of the cooperative-matrix attention kernels on this device,
/// if they may run there: cooperative matrices wanted (`matmul::coop_wanted`), FxFxF f16
/// fragments, subgroups of exactly F*F/8 invocations (each row belongs to F/8 lanes of one
/// subgroup) and subgroup shuffles.
fn coop_fragment(gpu: &Gpu) -> Option<u32> {
    let caps = gpu.caps();
    if !crate::ops::matmul::coop_wanted(caps) {
        return None;
    }
    let [f, _, _] = caps.coop_matrix_f16?;
    let fits = matches!(f, 16 | 8) && caps.subgroup_size_fits(f * f / 8) && caps.subgroup_shuffle;
    fits.then_some(f)
}

/// Whether f16 inputs of head width `d`, `nq` query and `nk` key rows over `segments`
/// segments, take the cooperative-matrix backward kernels on this device: where it has them
/// and both sides average at least [`COOP_MIN_ROWS_PER_SEGMENT`] rows per segment (each
/// kernel owns blocks of 32 rows of one side and stages tiles of 32 of the other).
pub fn coop_backward_chosen(gpu: &Gpu, d: usize, nq: usize, nk: usize, segments: usize) -> bool {
    let enough = COOP_MIN_ROWS_PER_SEGMENT * segments;
    nq >= enough && nk >= enough && coop_backward_kernels(gpu, d).is_some()
}

/// Which backward kernels f16 inputs of head width `d` run on this device, for `velox info`
/// and the benchmarks (segments of at least [`COOP_MIN_ROWS_PER_SEGMENT`] rows on average).
pub fn f16_backward_variant(gpu: &Gpu, d: usize) -> String {
    if coop_backward_kernels(gpu, d).is_some() {
        format!(
            "cooperative-matrix: S, dP = dO V^T, dV += P^T dO, dK += dS^T Q and dQ += dS K on f16 \
             fragments, f32 row statistics, dO, P and dS rounded to f16; blocks of \
             {COOP_BWD_BLOCK} rows, no atomics"
        )
    } else {
        format!("{}; f16 inputs widened to f32, f32 arithmetic", portable_variant(gpu, d, DType::F16))
    }
}

/// Segments averaging fewer query rows than this (the encoder's per-cell cross-attention has
/// one query per cell) run the portable kernel, whose invocations each own one row: a
/// cooperative-matrix block computes at least 32.
pub const COOP_MIN_ROWS_PER_SEGMENT: usize = 8;
/// Segments averaging at least this many query rows take the tall blocks.
pub const COOP_TALL_ROWS_PER_SEGMENT: usize = 64;
/// Segments averaging at least this many keys take the 64-key tiles (shorter ones would leave
/// most of a wide tile's scores masked).
pub const COOP_WIDE_KEYS_PER_SEGMENT: usize = 64;

/// The cooperative-matrix forward kernel that f16 inputs of head width `d`, `nq` query rows
/// and `nk` keys over `segments` segments, run on this device (with 64-key tiles only where
/// `wide` allows them: a recording's [`Recorder::wide_key_tiles`]); `None` where they run the
/// portable kernel.
pub fn coop_forward_chosen(
    gpu: &Gpu,
    d: usize,
    nq: usize,
    nk: usize,
    segments: usize,
    wide: bool,
) -> Option<CoopForward> {
    if nq < COOP_MIN_ROWS_PER_SEGMENT * segments {
        return None;
    }
    let tall = nq >= COOP_TALL_ROWS_PER_SEGMENT * segments;
    coop_forward_kernel(gpu, d, tall, wide && nk >= COOP_WIDE_KEYS_PER_SEGMENT * segments)
}

/// Which forward kernel f16 inputs of head width `d` run on this device, for `velox info` and
/// the benchmarks (segments of at least [`COOP_MIN_ROWS_PER_SEGMENT`] rows on average).
pub fn f16_forward_variant(gpu: &Gpu, d: usize) -> String {
    let Some(short) = coop_forward_kernel(gpu, d, false, false) else {
        return format!(
            "{}; f16 inputs widened to f32, f32 arithmetic",
            portable_variant(gpu, d, DType::F16)
        );
    };
    // What does not fit gives way to what does.
    let tall = coop_forward_kernel(gpu, d, true, false).map_or(short.rows, |c| c.rows);
    let wide = |tall| coop_forward_kernel(gpu, d, tall, true).map_or(short.keys, |c| c.keys);
    format!(
        "cooperative-matrix: S = QK^T and PV on f16 fragments, f32 softmax, P rounded to f16; \
         blocks of {} query rows, {tall} for segments of {COOP_TALL_ROWS_PER_SEGMENT} or more; \
         tiles of {} keys, {} in short and {} in tall blocks for segments of {COOP_WIDE_KEYS_PER_SEGMENT} \
         keys or more",
        short.rows,
        short.keys,
        wide(false),
        wide(true)
    )
}

/// Segments up to which a work list is built by one workgroup in one dispatch (the `build`
/// kernel walks them 256 at a time) rather than in four dispatches over the whole device.
pub const BUILD_MAX_SEGMENTS: usize = 4096;

/// The work list over the rows of `offsets` (blocks of `block` rows, one segment each):
/// returns the list and its capacity.
fn work_list(rec: &mut Recorder, offsets: &Tensor, rows: usize, block: usize) -> Result<(Tensor, usize)> {
    let gpu = offsets.gpu().clone();
    let segments = offsets.numel() - 1;
    let capacity = segments + rows.div_ceil(block);
    let list = Tensor::empty(&gpu, &[capacity, 2], DType::U32)?;
    let fit = |v: usize| fit_u32(v, || format!("{v} attention work items"));
    let p = BlockParams {
        segments: fit(segments)?,
        block: block as u32,
        rows: fit(rows)?,
        capacity: fit(capacity)?,
    };
    if segments <= BUILD_MAX_SEGMENTS {
        rec.dispatch(
            kernels::ATTENTION_BLOCKS_BUILD,
            [1, 1, 1],
            args::AttentionBlocksBuildArgs { offsets, list: &list },
            &p,
        )?;
        return Ok((list, capacity));
    }
    let items = Tensor::empty(&gpu, &[segments], DType::U32)?;
    let first = Tensor::empty(&gpu, &[segments], DType::U32)?;
    let groups = (segments as u64).div_ceil(256);
    fill_bits(rec, &list, u32::MAX)?;
    rec.dispatch_linear(
        kernels::ATTENTION_BLOCKS_COUNT,
        groups,
        args::AttentionBlocksCountArgs { offsets, items: &items },
        &p,
    )?;
    exclusive_scan(rec, &items, &first)?;
    rec.dispatch_linear(
        kernels::ATTENTION_BLOCKS_WRITE,
        groups,
        args::AttentionBlocksWriteArgs { offsets, first_item: &first, list: &list },
        &p,
    )?;
    Ok((list, capacity))
}

/// Softmax(q k^T * scale) v per segment and head. Records the work; nothing runs until the
/// recorder is submitted. q, k and v are all f32, or all f16 (the f16 model path: the inputs
/// are read as f16, everything else is f32, and o and lse are f32 either way).
pub fn attention(
    rec: &mut Recorder,
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    seg: &Segments,
    scale: f32,
) -> Result<AttentionOut> {
    let (nq, nk, h, d) = check(q, k, v, seg)?;
    let gpu = q.gpu().clone();
    let o = Tensor::empty(&gpu, &[nq, h, d], DType::F32)?;
    let lse = Tensor::empty(&gpu, &[nq, h], DType::F32)?;
    if nq == 0 || h == 0 {
        return Ok(AttentionOut { o, lse });
    }
    let kern = kernels_for(d).expect("checked");
    let portable = match cpu_kernels(&gpu, d, q.dtype()) {
        Some(cpu) => (cpu.fwd, CPU_BLOCK),
        None if q.dtype() == DType::F16 => (kern.fwd_f16, BLOCK),
        None => (kern.fwd, BLOCK),
    };
    let (kernel, block) = match q.dtype() {
        DType::F16 => {
            let wide = rec.wide_key_tiles();
            coop_forward_chosen(&gpu, d, nq, nk, seg.count(), wide).map_or(portable, |c| (c.kernel, c.rows))
        }
        _ => portable,
    };
    let (list, capacity) = seg.work_list(rec, false, nq, block)?;
    let p = params(h, capacity, scale, nq, nk)?;
    let (q_off, k_off) = (&seg.q_offsets, &seg.k_offsets);
    let args = args::AttentionD16FwdArgs { q, k, v, q_off, k_off, work: &list, o: &o, lse: &lse };
    rec.dispatch_linear(kernel, (capacity * h) as u64, args, &p)?;
    Ok(AttentionOut { o, lse })
}

fn params(h: usize, capacity: usize, scale: f32, nq: usize, nk: usize) -> Result<Params> {
    let items = capacity.checked_mul(h).and_then(|v| u32::try_from(v).ok()).ok_or_else(|| {
        Error::too_large(Limit::Index, format!("{capacity} attention work items x {h} heads"))
    })?;
    if !scale.is_finite() {
        return Err(Error::Invalid(format!("attention scale {scale} is not finite")));
    }
    Ok(Params { heads: h as u32, items, scale, nq: nq as u32, nk: nk as u32 })
}

/// Gradients of a loss with respect to q, k and v, given dO = dL/do and the forward outputs.
/// q, k and v are all f32 or all f16 (read as f16, as in the forward pass); dO, o, lse and the
/// gradients are f32.
#[allow(clippy::too_many_arguments)]
pub fn attention_backward(
    rec: &mut Recorder,
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    out: &AttentionOut,
    d_o: &Tensor,
    seg: &Segments,
    scale: f32,
) -> Result<AttentionGrads> {
    // Shaped like q, k and v; `attention_backward_into` checks every shape.
    let f32_like = |t: &Tensor| Tensor::empty(t.gpu(), t.shape(), DType::F32);
    let grads = AttentionGrads { dq: f32_like(q)?, dk: f32_like(k)?, dv: f32_like(v)? };
    attention_backward_into(rec, q, k, v, out, d_o, seg, scale, &grads)?;
    Ok(grads)
}

/// [`attention_backward`] into given tensors (f32, `dq` like q, `dk` and `dv` like k; views
/// of one buffer, say, for projections stacked in one product).
#[allow(clippy::too_many_arguments)]
pub fn attention_backward_into(
    rec: &mut Recorder,
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    out: &AttentionOut,
    d_o: &Tensor,
    seg: &Segments,
    scale: f32,
    grads: &AttentionGrads,
) -> Result<()> {
    let (nq, nk, h, d) = check(q, k, v, seg)?;
    for (what, t) in [("dO", d_o), ("o", &out.o), ("lse", &out.lse)] {
        if t.dtype() != DType::F32 {
            return Err(Error::Shape(format!("attention backward: {what} {t:?} must be f32")));
        }
    }
    if d_o.shape() != q.shape() || out.o.shape() != q.shape() || out.lse.shape() != [nq, h] {
        return Err(Error::Shape(format!(
            "attention backward: dO {d_o:?}, o {:?} and lse {:?} must match q {q:?}",
            out.o, out.lse
        )));
    }
    let AttentionGrads { dq, dk, dv } = grads;
    for (what, t, like) in [("dq", dq, q), ("dk", dk, k), ("dv", dv, v)] {
        if t.dtype() != DType::F32 || t.shape() != like.shape() {
            return Err(Error::Shape(format!(
                "attention backward: {what} {t:?} must be f32 shaped like {like:?}"
            )));
        }
    }
    let gpu = q.gpu().clone();
    if h == 0 {
        return Ok(());
    }
    // Keys outside every segment get no gradient from the kernels: start from zeros, unless
    // the segments hold every key.
    if seg.all_keys != Some(nk) {
        fill_bits(rec, dk, 0)?;
        fill_bits(rec, dv, 0)?;
    }
    let delta = Tensor::empty(&gpu, &[nq, h], DType::F32)?;
    let kern = kernels_for(d).expect("checked");
    let coop = q.dtype() == DType::F16 && coop_backward_chosen(&gpu, d, nq, nk, seg.count());
    let (dq_kernel, dkv_kernel, block) = match cpu_kernels(&gpu, d, q.dtype()) {
        _ if coop => {
            let (dq, dkv) = coop_backward_kernels(&gpu, d).expect("chosen");
            (dq, dkv, COOP_BWD_BLOCK)
        }
        Some(cpu) => (cpu.dq, cpu.dkv, CPU_BLOCK),
        None if q.dtype() == DType::F16 => (kern.dq_f16, kern.dkv_f16, BLOCK),
        None => (kern.dq, kern.dkv, BLOCK),
    };
    let (o, lse) = (&out.o, &out.lse);
    if nq > 0 {
        let (q_list, q_capacity) = seg.work_list(rec, false, nq, block)?;
        let p = params(h, q_capacity, scale, nq, nk)?;
        let (q_off, k_off, work) = (&seg.q_offsets, &seg.k_offsets, &q_list);
        let args =
            args::AttentionD16BwdDqArgs { q, k, v, q_off, k_off, work, o, lse, d_o, delta: &delta, dq };
        rec.dispatch_linear(dq_kernel, (q_capacity * h) as u64, args, &p)?;
    }
    if nk > 0 {
        let (k_list, k_capacity) = seg.work_list(rec, true, nk, block)?;
        let p = params(h, k_capacity, scale, nq, nk)?;
        let (q_off, k_off, work) = (&seg.q_offsets, &seg.k_offsets, &k_list);
        let args =
            args::AttentionD16BwdDkvArgs { q, k, v, q_off, k_off, work, lse, d_o, delta: &delta, dk, dv };
        rec.dispatch_linear(dkv_kernel, (k_capacity * h) as u64, args, &p)?;
    }
    Ok(())
}

/// FLOPs of the forward pass (two matmuls of 2 flops per multiply-add) for given segment
/// lengths, used by benchmarks.
pub fn forward_flops(q_lens: &[usize], k_lens: &[usize], heads: usize, d: usize) -> f64 {
    q_lens.iter().zip(k_lens).map(|(&a, &b)| 4.0 * a as f64 * b as f64 * (heads * d) as f64).sum()
}

pub mod reference {
    //! Attention in f64 with explicit probabilities, and its backward pass.

    /// Offsets from lengths.
    pub fn offsets(lens: &[usize]) -> Vec<usize> {
        let mut out = vec![0];
        for &l in lens {
            out.push(out.last().unwrap() + l);
        }
        out
    }

    /// (o, lse) for q [nq,h,d], k/v [nk,h,d] (flat), segment offsets.
    #[allow(clippy::too_many_arguments)]
    pub fn attention(
        q: &[f64],
        k: &[f64],
        v: &[f64],
        q_off: &[usize],
        k_off: &[usize],
        h: usize,
        d: usize,
        scale: f64,
    ) -> (Vec<f64>, Vec<f64>) {
        let nq = q.len() / (h * d);
        let mut o = vec![0.0; q.len()];
        let mut lse = vec![f64::NEG_INFINITY; nq * h];
        for s in 0..q_off.len() - 1 {
            for i in q_off[s]..q_off[s + 1] {
                for hh in 0..h {
                    let qi = &q[(i * h + hh) * d..][..d];
                    let scores: Vec<f64> = (k_off[s]..k_off[s + 1])
                        .map(|j| {
                            scale
                                * qi.iter().zip(&k[(j * h + hh) * d..][..d]).map(|(a, b)| a * b).sum::<f64>()
                        })
                        .collect();
                    if scores.is_empty() {
                        continue;
                    }
                    let m = scores.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                    let l: f64 = scores.iter().map(|x| (x - m).exp()).sum();
                    lse[i * h + hh] = m + l.ln();
                    for (jj, j) in (k_off[s]..k_off[s + 1]).enumerate() {
                        let p = (scores[jj] - m).exp() / l;
                        for c in 0..d {
                            o[(i * h + hh) * d + c] += p * v[(j * h + hh) * d + c];
                        }
                    }
                }
            }
        }
        (o, lse)
    }

    /// (dq, dk, dv) given dO, by the chain rule through the explicit softmax.
    #[allow(clippy::too_many_arguments)]
    pub fn attention_backward(
        q: &[f64],
        k: &[f64],
        v: &[f64],
        d_o: &[f64],
        q_off: &[usize],
        k_off: &[usize],
        h: usize,
        d: usize,
        scale: f64,
    ) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let (mut dq, mut dk, mut dv) = (vec![0.0; q.len()], vec![0.0; k.len()], vec![0.0; v.len()]);
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        for s in 0..q_off.len() - 1 {
            let keys: Vec<usize> = (k_off[s]..k_off[s + 1]).collect();
            if keys.is_empty() {
                continue;
            }
            for i in q_off[s]..q_off[s + 1] {
                for hh in 0..h {
                    let row = |t: &[f64], r: usize| -> Vec<f64> { t[(r * h + hh) * d..][..d].to_vec() };
                    let (qi, gi) = (row(q, i), row(d_o, i));
                    let scores: Vec<f64> = keys.iter().map(|&j| scale * dot(&qi, &row(k, j))).collect();
                    let m = scores.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                    let l: f64 = scores.iter().map(|x| (x - m).exp()).sum();
                    let p: Vec<f64> = scores.iter().map(|x| (x - m).exp() / l).collect();
                    let dp: Vec<f64> = keys.iter().map(|&j| dot(&gi, &row(v, j))).collect();
                    let delta: f64 = p.iter().zip(&dp).map(|(a, b)| a * b).sum();
                    for (jj, &j) in keys.iter().enumerate() {
                        let ds = p[jj] * (dp[jj] - delta);
                        for c in 0..d {
                            dv[(j * h + hh) * d + c] += p[jj] * gi[c];
                            dq[(i * h + hh) * d + c] += scale * ds * k[(j * h + hh) * d + c];
                            dk[(j * h + hh) * d + c] += scale * ds * qi[c];
                        }
                    }
                }
            }
        }
        (dq, dk, dv)
    }
}
