//! Batched matrix multiply with f32 accumulation. Kernels: `shaders/matmul.wgsl` (tiled, every
//! device, f32 or f16 operands), `shaders/matmul_small.wgsl` (f32 operands when M or N is 64 or
//! less: 32x32 or 64x64 tiles) and `shaders/matmul_coop.wgsl` (f16 operands on cooperative matrices,
//! where the device has them). A product with few output tiles and a long K (a weight gradient
//! over many rows) is split along K into pieces summed afterwards ([`split_k`]), so the whole
//! device works on it.
//!
//! `a` is `[M, K]` (`[K, M]` when `trans_a`), `b` is `[K, N]` (`[N, K]` when `trans_b`), either
//! with an optional leading batch dimension; an operand without one (or with batch 1) is
//! broadcast over the other's batch, which is how `x @ W` runs for a batch of `x`. The output is
//! f32 `[.., M, N]`.
//!
//! Tests: the harness's `matmul` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/matmul.rs` (f16 and cooperative kernels,
//! split-K, narrow tiles, large dispatches).

use crate::caps::Caps;
use crate::device::Gpu;
use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{
    Kernel, MATMUL_COOP8_ROWS128_COLS128_FRAG_COLS2_MAIN, MATMUL_COOP8_ROWS128_COLS128_FRAG_COLS4_MAIN,
    MATMUL_COOP8_ROWS128_COLS64_FRAG_COLS2_MAIN, MATMUL_COOP8_ROWS64_COLS128_FRAG_COLS2_MAIN,
    MATMUL_COOP8_ROWS64_COLS64_FRAG_COLS2_MAIN, MATMUL_COOP_ROWS128_COLS128_FRAG_COLS2_MAIN,
    MATMUL_COOP_ROWS128_COLS128_FRAG_COLS4_MAIN, MATMUL_COOP_ROWS128_COLS64_FRAG_COLS2_MAIN,
    MATMUL_COOP_ROWS64_COLS128_FRAG_COLS2_MAIN, MATMUL_COOP_ROWS64_COLS64_FRAG_COLS2_MAIN,
    MATMUL_CPU_LAYOUT0_COLS1_MAIN, MATMUL_CPU_LAYOUT0_COLS2_MAIN, MATMUL_CPU_LAYOUT0_COLS4_MAIN,
    MATMUL_CPU_LAYOUT1_COLS1_MAIN, MATMUL_CPU_LAYOUT1_COLS2_MAIN, MATMUL_CPU_LAYOUT1_COLS4_MAIN,
    MATMUL_CPU_LAYOUT2_COLS1_MAIN, MATMUL_CPU_LAYOUT2_COLS2_MAIN, MATMUL_CPU_LAYOUT2_COLS4_MAIN,
    MATMUL_FLAG_A_SCALAR, MATMUL_FLAG_BIAS, MATMUL_FLAG_BIAS_PER_ENTRY, MATMUL_FLAG_B_SCALAR,
    MATMUL_FLAG_SUMMED, MATMUL_FLAG_TRANS_A, MATMUL_FLAG_TRANS_B, MATMUL_MAIN, MATMUL_MAIN_F16,
    MATMUL_ROWS_MAIN, MATMUL_SMALL_TS32_MAIN, MATMUL_SMALL_TS64_MAIN,
};
use crate::ops::binary::{binary_into, Binary};
use crate::ops::reduce::{reduce_into, Reduce};
use crate::recorder::{NarrowMatmul, Recorder};
use crate::tensor::{DType, Tensor};
use crate::Limit;

/// Output tile of one workgroup: the tiled and cooperative-matrix kernels.
const TILE: usize = 128;
/// A product whose M or N is at most this uses the narrow-tile kernel (f32 operands): a
/// 128x128 tile would be mostly empty. Its tile is 32x32 when the narrow side is 32 or less,
/// else 64x64 (4x4 outputs per invocation, twice the arithmetic per shared-memory read).
/// On CPU devices such products take `matmul_rows.wgsl` instead (see [`NarrowMatmul`]): rows of
/// ROWS_NC outputs, ROWS_WG rows per workgroup.
const NARROW: usize = 64;
const NARROW_32: usize = 32;
const ROWS_NC: usize = 16;
const ROWS_WG: usize = 64;
/// Output tile of the CPU kernel (`matmul_cpu.wgsl`): 8 rows x 32 COLS columns, one SIMD group.
const CPU_ROWS: usize = 8;
/// The CPU kernel's variants, by layout (see [`cpu_kernel`]) and COLS = 1, 2, 4.
const CPU_KERNELS: [[TiledKernel; 3]; 3] = [
    [MATMUL_CPU_LAYOUT0_COLS1_MAIN, MATMUL_CPU_LAYOUT0_COLS2_MAIN, MATMUL_CPU_LAYOUT0_COLS4_MAIN],
    [MATMUL_CPU_LAYOUT1_COLS1_MAIN, MATMUL_CPU_LAYOUT1_COLS2_MAIN, MATMUL_CPU_LAYOUT1_COLS4_MAIN],
    [MATMUL_CPU_LAYOUT2_COLS1_MAIN, MATMUL_CPU_LAYOUT2_COLS2_MAIN, MATMUL_CPU_LAYOUT2_COLS4_MAIN],
];
/// The cooperative-matrix kernels for one fragment size (`shaders/matmul_coop.wgsl`'s and
/// `matmul_coop8.wgsl`'s variants).
struct CoopKernels {
    /// F of the FxFxF fragments.
    fragment: u32,
    /// By output tile, `[rows == 128][cols == 128]`, each side 64 or 128; every subgroup owns
    /// 4 x 2 fragments of its tile.
    tiles: [[CoopKernel; 2]; 2],
    /// The 128 x 128 tile with 4 x 4 fragments a subgroup (64 x 64 at F = 16), which large
    /// products take (docs/decisions/kernels.md, "subgroup blocks").
    wide_blocks: CoopKernel,
}

const COOP_KERNELS: [CoopKernels; 2] = [
    CoopKernels {
        fragment: 16,
        tiles: [
            [MATMUL_COOP_ROWS64_COLS64_FRAG_COLS2_MAIN, MATMUL_COOP_ROWS64_COLS128_FRAG_COLS2_MAIN],
            [MATMUL_COOP_ROWS128_COLS64_FRAG_COLS2_MAIN, MATMUL_COOP_ROWS128_COLS128_FRAG_COLS2_MAIN],
        ],
        wide_blocks: MATMUL_COOP_ROWS128_COLS128_FRAG_COLS4_MAIN,
    },
    CoopKernels {
        fragment: 8,
        tiles: [
            [MATMUL_COOP8_ROWS64_COLS64_FRAG_COLS2_MAIN, MATMUL_COOP8_ROWS64_COLS128_FRAG_COLS2_MAIN],
            [MATMUL_COOP8_ROWS128_COLS64_FRAG_COLS2_MAIN, MATMUL_COOP8_ROWS128_COLS128_FRAG_COLS2_MAIN],
        ],
        wide_blocks: MATMUL_COOP8_ROWS128_COLS128_FRAG_COLS4_MAIN,
    },
];
/// A product with at most this many output rows (columns) takes a cooperative tile of 64 rows
/// (columns): a 128-wide side would be at least half empty (docs/decisions/kernels.md).
const COOP_HALF: usize = 64;
/// The cooperative-matrix kernel reads its operands 8 halves (16 bytes) at a time.
const COOP_VECTOR: usize = 8;

// Push constants of both kernels (`Params` in the shaders); strides are in elements.
use crate::kernels::params::MatmulParams as Params;

/// The tiled kernels: operands, output and a bias binding.
type TiledKernel = Kernel<Params, args::MatmulMainArgs<'static>>;
/// The cooperative-matrix kernels: operands and output (they take no bias; every tile variant
/// shares the first variant's binding struct).
pub type CoopKernel = Kernel<Params, args::MatmulCoopRows64Cols64FragCols2MainArgs<'static>>;

/// A matmul kernel, by interface. Every one takes the push constants of
/// `shaders/include/matmul_params.wgsl`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum MatmulKernel {
    Tiled(TiledKernel),
    Coop(CoopKernel),
}

impl MatmulKernel {
    fn is(self, k: TiledKernel) -> bool {
        self == MatmulKernel::Tiled(k)
    }

    /// The CPU kernel (any layout): it sums a batch itself and splits nothing along K.
    fn is_cpu(self) -> bool {
        self.cpu_layout().is_some()
    }

    /// The CPU kernel's layout and output columns per workgroup, `None` for other kernels.
    fn cpu_layout(self) -> Option<(usize, usize)> {
        CPU_KERNELS
            .iter()
            .enumerate()
            .find_map(|(layout, ks)| ks.iter().position(|k| self.is(*k)).map(|c| (layout, 32 << c)))
    }

    /// Whether the kernel has a bias binding (read where `MATMUL_FLAG_BIAS` is set).
    fn takes_bias(self) -> bool {
        matches!(self, MatmulKernel::Tiled(_))
    }

    /// Records the kernel; `bias` is bound where the kernel has the binding.
    fn dispatch(
        self,
        rec: &mut Recorder,
        groups: [u32; 3],
        [a, b, out, bias]: [&Tensor; 4],
        params: &Params,
    ) -> Result<()> {
        match self {
            MatmulKernel::Tiled(k) => {
                rec.dispatch(k, groups, args::MatmulMainArgs { a, b, out, bias }, params)
            }
            MatmulKernel::Coop(k) => {
                rec.dispatch(k, groups, args::MatmulCoopRows64Cols64FragCols2MainArgs { a, b, out }, params)
            }
        }
    }
}

impl Params {
    /// The push constants of a product of plan `p` (strides from the transposes; no bias, the
    /// first batch entry first). The caller has checked every size fits in u32.
    fn of(p: &Plan, trans_a: bool, trans_b: bool, accumulate: bool) -> Params {
        Params {
            m: p.m as u32,
            n: p.n as u32,
            k: p.k as u32,
            accumulate: accumulate as u32,
            a_row: if trans_a { 1 } else { p.k as u32 },
            a_col: if trans_a { p.m as u32 } else { 1 },
            a_batch: p.a_batch_stride as u32,
            b_row: if trans_b { 1 } else { p.n as u32 },
            b_col: if trans_b { p.k as u32 } else { 1 },
            b_batch: p.b_batch_stride as u32,
            flags: if trans_a { MATMUL_FLAG_TRANS_A } else { 0 }
                | if trans_b { MATMUL_FLAG_TRANS_B } else { 0 },
            batch_base: 0,
        }
    }
}

/// The sizes of one product, checked.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Plan {
    pub batch: usize,
    pub m: usize,
    pub n: usize,
    pub k: usize,
    /// Elements between consecutive batch entries of `a` and `b` (0 when broadcast).
    pub a_batch_stride: usize,
    pub b_batch_stride: usize,
    pub out_shape: Vec<usize>,
}

/// Checks the shapes of `op(a) @ op(b)` and works out the sizes.
pub fn plan(a: &[usize], b: &[usize], trans_a: bool, trans_b: bool) -> Result<Plan> {
    let split = |s: &[usize], what: &str| -> Result<(Option<usize>, usize, usize)> {
        match *s {
            [r, c] => Ok((None, r, c)),
            [bt, r, c] => Ok((Some(bt), r, c)),
            _ => Err(Error::Shape(format!(
                "matmul: {what} must be 2D [rows, cols] or 3D [batch, rows, cols], got {s:?}"
            ))),
        }
    };
    let (a_batch, a_r, a_c) = split(a, "a")?;
    let (b_batch, b_r, b_c) = split(b, "b")?;
    let (m, k) = if trans_a { (a_c, a_r) } else { (a_r, a_c) };
    let (k_b, n) = if trans_b { (b_c, b_r) } else { (b_r, b_c) };
    if k != k_b {
        return Err(Error::Shape(format!(
            "matmul: inner sizes differ: a {a:?}{} has K = {k}, b {b:?}{} has K = {k_b}",
            if trans_a { " (transposed)" } else { "" },
            if trans_b { " (transposed)" } else { "" },
        )));
    }
    let batch = match (a_batch, b_batch) {
        (None, None) => None,
        (Some(x), None) | (None, Some(x)) => Some(x),
        (Some(x), Some(y)) if x == y || y == 1 => Some(x),
        (Some(1), Some(y)) => Some(y),
        (Some(x), Some(y)) => {
            return Err(Error::Shape(format!(
                "matmul: batch sizes differ: a {a:?} has {x}, b {b:?} has {y} (one may be 1 or absent to broadcast)"
            )))
        }
    };
    let stride = |bt: Option<usize>, size: usize| match bt {
        Some(x) if x > 1 => size,
        _ => 0,
    };
    let out_shape = match batch {
        Some(bt) => vec![bt, m, n],
        None => vec![m, n],
    };
    Ok(Plan {
        batch: batch.unwrap_or(1),
        m,
        n,
        k,
        a_batch_stride: stride(a_batch, m * k),
        b_batch_stride: stride(b_batch, k * n),
        out_shape,
    })
}

/// The cooperative-matrix kernels this device can run (see [`COOP_KERNELS`]), if any. The
/// kernels exist for FxFxF fragments with F = 16 (`matmul_coop.wgsl`) and F = 8
/// (`matmul_coop8.wgsl`). Each splits its workgroup into subgroups of exactly F*F/8 (32 or 8),
/// each subgroup owning a block of fragments of the tile, so they are chosen only where a
/// pipeline can have that size: the device's only one, or one it can be asked for (the pipeline
/// then requests it). The 128x128 tile in 4 x 2 blocks declares the most workgroup memory: the
/// others fit where it does.
fn coop_kernels(caps: &Caps) -> Option<&'static CoopKernels> {
    if !coop_wanted(caps) {
        return None;
    }
    let [f, _, _] = caps.coop_matrix_f16?;
    let kernels = COOP_KERNELS.iter().find(|k| k.fragment == f)?;
    let most = kernels.tiles[1][1].info().shared_bytes.max(kernels.wide_blocks.info().shared_bytes);
    let fits = caps.subgroup_size_fits(f * f / 8) && caps.max_shared_memory >= most;
    fits.then_some(kernels)
}

/// The cooperative-matrix kernel this device runs large products on (its 128x128 tile, in
/// 4 x 4 blocks), if any.
pub fn coop_kernel(caps: &Caps) -> Option<CoopKernel> {
    coop_kernels(caps).map(|k| k.wide_blocks)
}

/// The cooperative-matrix kernel for an output of `m` rows and `n` columns: a side of at most
/// [`COOP_HALF`] takes the 64-wide tile; the 128 x 128 tile takes 4 x 4 fragments a subgroup
/// where `wide_blocks` (a recording's [`Recorder::wide_matmul_blocks`]), else 4 x 2.
pub fn coop_kernel_for(caps: &Caps, m: usize, n: usize, wide_blocks: bool) -> Option<CoopKernel> {
    coop_kernels(caps).map(|k| match (m > COOP_HALF, n > COOP_HALF) {
        (true, true) if wide_blocks => k.wide_blocks,
        (tall, wide) => k.tiles[tall as usize][wide as usize],
    })
}

/// Output rows and columns of one workgroup of a cooperative-matrix kernel.
fn coop_tile(kernel: CoopKernel) -> (usize, usize) {
    COOP_KERNELS
        .iter()
        .find_map(|k| {
            let tile = k.tiles.iter().enumerate().find_map(|(rows, ks)| {
                ks.iter().position(|&x| x == kernel).map(|cols| (64 << rows, 64 << cols))
            });
            tile.or((k.wide_blocks == kernel).then_some((128, 128)))
        })
        .expect("a cooperative-matrix kernel")
}

/// Whether the cooperative-matrix kernels (matmul, attention) may be chosen on this device at
/// all: not where the CPU kernel variants run (`Caps::cpu_kernels`, a CPU device unless
/// `VELOX_CPU_KERNELS=0`). lavapipe from Mesa 26 offers 8x8x8 fragments, emulated: there the
/// cooperative f16 matmul takes 2.9 ms at 256^3 where the tiled f16 kernel takes 1.9 and the
/// CPU f32 kernel 0.72, and the cooperative attention 3 to 10 times the CPU kernels' time
/// (docs/decisions/kernels.md). `VELOX_CPU_KERNELS=0` runs them there, which is how
/// `tools/coop-check.sh` tests them.
pub fn coop_wanted(caps: &Caps) -> bool {
    !caps.cpu_kernels
}

/// Whether the device can run a cooperative-matrix matmul kernel at all.
pub fn coop_eligible(caps: &Caps) -> bool {
    coop_kernel(caps).is_some()
}

/// Whether one product's layout suits the cooperative-matrix kernel: the contiguous axis of each
/// operand must be a multiple of 8 so that 16-byte reads never straddle a row.
pub fn coop_layout_ok(p: &Plan, trans_a: bool, trans_b: bool) -> bool {
    let a_inner = if trans_a { p.m } else { p.k };
    let b_inner = if trans_b { p.k } else { p.n };
    a_inner % COOP_VECTOR == 0 && b_inner % COOP_VECTOR == 0
}

/// Which kernel a product of `dtype` operands runs on this device, for `velox info`.
pub fn matmul_variant(gpu: &Gpu, dtype: DType) -> &'static str {
    match dtype {
        DType::F32 if gpu.caps().texel_kernels() && cpu_kernel_fits(gpu.caps()) => {
            "CPU kernel: 8 rows x 32, 64 or 128 columns per SIMD group of 8, operands read through \
             texel buffers (vec4s where their contiguous axis is a multiple of 4, else one value at a \
             time), A shared by subgroup shuffles, 8 k a step (CPU device)"
        }
        DType::F32 if gpu.caps().cpu_kernels => {
            "tiled f32: 128x128 tile per 256 invocations, 8x8 per invocation, k step 8; \
             when M or N <= 64, 16 outputs of a row per invocation, no workgroup memory (CPU device)"
        }
        DType::F32 => {
            "tiled f32: 128x128 tile per 256 invocations, 8x8 per invocation, k step 8 \
             (32x32 tiles when M or N <= 32, 64x64 when <= 64)"
        }
        DType::F16 if coop_kernel(gpu.caps()).is_some_and(|k| gpu.supports(k)) => {
            if coop_kernel(gpu.caps()) == Some(MATMUL_COOP_ROWS128_COLS128_FRAG_COLS4_MAIN) {
                "cooperative-matrix f16 x f16 -> f32: 128x128 tile in 64x64 a subgroup (128x64, \
                 64x128 or 64x64 tiles in 64x32 a subgroup where N or M is at most 64), 16x16x16 \
                 fragments, k step 32, split along K where few tiles walk a long K (tiled f16 \
                 fallback where an operand's contiguous axis is not a multiple of 8)"
            } else {
                "cooperative-matrix f16 x f16 -> f32: 128x128 tile in 32x32 a subgroup (128x64, \
                 64x128 or 64x64 tiles in 32x16 a subgroup where N or M is at most 64), 8x8x8 \
                 fragments, k step 16, split along K where few tiles walk a long K (tiled f16 \
                 fallback where an operand's contiguous axis is not a multiple of 8)"
            }
        }
        DType::F16 => "tiled f16 x f16 -> f32 (f16 read as packed words, f32 accumulation)",
        _ => "none: matmul takes f32 or f16 operands",
    }
}

/// `op(a) @ op(b)` into a new f32 tensor.
pub fn matmul(rec: &mut Recorder, a: &Tensor, b: &Tensor, trans_a: bool, trans_b: bool) -> Result<Tensor> {
    new_product(rec, a, b, trans_a, trans_b, None)
}

/// `op(a) @ op(b) + bias` into a new f32 tensor: `bias` is f32 with one value per output column
/// (a linear layer's bias), added to every row; or, for a batched product, one such row per
/// batch entry (`[batch, N]`: a stack of linear layers). The tiled and narrow-tile kernels add
/// it as they write their outputs (a bias per entry: the narrow-side kernel); elsewhere
/// (cooperative matrices, products split along K) it is a separate add.
pub fn matmul_bias(
    rec: &mut Recorder,
    a: &Tensor,
    b: &Tensor,
    trans_a: bool,
    trans_b: bool,
    bias: &Tensor,
) -> Result<Tensor> {
    new_product(rec, a, b, trans_a, trans_b, Some(bias))
}

fn new_product(
    rec: &mut Recorder,
    a: &Tensor,
    b: &Tensor,
    trans_a: bool,
    trans_b: bool,
    bias: Option<&Tensor>,
) -> Result<Tensor> {
    let p = plan(a.shape(), b.shape(), trans_a, trans_b)?;
    check_dtypes(a, b)?;
    let out = Tensor::empty(a.gpu(), &p.out_shape, DType::F32)?;
    product(rec, a, b, trans_a, trans_b, &out, false, bias)?;
    Ok(out)
}

/// `out = op(a) @ op(b)`, or `out += op(a) @ op(b)` when `accumulate` (gradient accumulation).
/// `out` must be f32 with the product's shape and must not share storage with `a` or `b`.
pub fn matmul_into(
    rec: &mut Recorder,
    a: &Tensor,
    b: &Tensor,
    trans_a: bool,
    trans_b: bool,
    out: &Tensor,
    accumulate: bool,
) -> Result<()> {
    product(rec, a, b, trans_a, trans_b, out, accumulate, None)
}

/// `out (+)= op(a) @ op(b) + bias`: [`matmul_into`] with a linear layer's bias (f32, one value
/// per output column), added as the kernels write where they can. Accumulating onto a residual
/// copied into `out` is a pre-norm block's `x + f(x) W + b` in one product.
#[allow(clippy::too_many_arguments)]
pub fn matmul_bias_into(
    rec: &mut Recorder,
    a: &Tensor,
    b: &Tensor,
    trans_a: bool,
    trans_b: bool,
    bias: Option<&Tensor>,
    out: &Tensor,
    accumulate: bool,
) -> Result<()> {
    product(rec, a, b, trans_a, trans_b, out, accumulate, bias)
}

/// `out (+)= sum_i op(a[i]) @ op(b[i])` over the batch entries of a batched product (`out`
/// f32 `[M, N]`): the input gradient of a stack of linear layers that read one input. One
/// dispatch where the kernel sums the entries itself (the narrow-side kernel on CPU devices),
/// else the batched product and a sum over the batch.
pub fn matmul_sum_into(
    rec: &mut Recorder,
    a: &Tensor,
    b: &Tensor,
    trans_a: bool,
    trans_b: bool,
    out: &Tensor,
    accumulate: bool,
) -> Result<()> {
    let p = plan(a.shape(), b.shape(), trans_a, trans_b)?;
    check_dtypes(a, b)?;
    check_out(a, b, out, &[p.m, p.n])?;
    let kernel = choose_kernel(a, b, &p, trans_a, trans_b, rec);
    let fits = u32::try_from(p.batch).is_ok() && [a, b].iter().all(|t| t.numel() <= u32::MAX as usize);
    if !(kernel.is(MATMUL_ROWS_MAIN) || kernel.is_cpu()) || !fits || p.m == 0 || p.n == 0 {
        let parts = Tensor::empty(a.gpu(), &p.out_shape, DType::F32)?;
        product(rec, a, b, trans_a, trans_b, &parts, false, None)?;
        let parts = parts.reshape(&[p.batch, p.m, p.n])?;
        return reduce_into(rec, &parts, 0, Reduce::Sum, out, accumulate);
    }
    let groups = grid(a.gpu(), kernel, &p, 1)?;
    let base = Params::of(&p, trans_a, trans_b, accumulate);
    let flags = base.flags | MATMUL_FLAG_SUMMED | cpu_flags(kernel, &p, trans_a, trans_b);
    let params = Params { flags, batch_base: p.batch as u32, ..base };
    let g = [groups[0] as u32, groups[1] as u32, 1];
    // The bias binding is unused (MATMUL_FLAG_BIAS clear): b stands in.
    kernel.dispatch(rec, g, [a, b, out, b], &params)
}

/// Fails unless `out` is f32 of `shape` and apart from the operands.
fn check_out(a: &Tensor, b: &Tensor, out: &Tensor, shape: &[usize]) -> Result<()> {
    if out.dtype() != DType::F32 {
        return Err(Error::DType(format!("matmul: out must be f32 {shape:?}, got {out:?}")));
    }
    if out.shape() != shape {
        return Err(Error::Shape(format!("matmul: out must be f32 {shape:?}, got {out:?}")));
    }
    if out.same_storage(a) || out.same_storage(b) {
        return Err(Error::Shape(
            "matmul: out shares storage with an operand; write into a separate tensor".into(),
        ));
    }
    Ok(())
}

/// The workgroups of a product of plan `p` on `kernel`, `z` layers deep: columns, rows and
/// layers, the first two checked against the device's limits.
fn grid(gpu: &Gpu, kernel: MatmulKernel, p: &Plan, z: usize) -> Result<[usize; 3]> {
    // Output rows and columns of one workgroup.
    let (tm, tn) = match kernel {
        k if k.is(MATMUL_SMALL_TS32_MAIN) => (32, 32),
        k if k.is(MATMUL_SMALL_TS64_MAIN) => (64, 64),
        k if k.is(MATMUL_ROWS_MAIN) => (ROWS_WG, ROWS_NC),
        k if k.is_cpu() => (CPU_ROWS, k.cpu_layout().expect("a CPU kernel").1),
        MatmulKernel::Coop(k) => coop_tile(k),
        _ => (TILE, TILE),
    };
    let groups = [p.n.div_ceil(tn), p.m.div_ceil(tm), z];
    let max = gpu.caps().max_workgroup_count;
    if groups[..2].iter().zip(max).any(|(&g, lim)| g > lim as usize) {
        return Err(Error::too_large(
            Limit::Workgroups,
            format!(
                "matmul: [{}, {}] outputs need {groups:?} workgroups of {tm}x{tn}, the device allows {max:?}",
                p.m, p.n
            ),
        ));
    }
    Ok(groups)
}

#[allow(clippy::too_many_arguments)]
fn product(
    rec: &mut Recorder,
    a: &Tensor,
    b: &Tensor,
    trans_a: bool,
    trans_b: bool,
    out: &Tensor,
    accumulate: bool,
    bias: Option<&Tensor>,
) -> Result<()> {
    let p = plan(a.shape(), b.shape(), trans_a, trans_b)?;
    // One bias row for every batch entry, or one per entry (a stack of linear layers).
    let per_entry = bias.is_some_and(|b| p.batch > 1 && b.numel() == p.batch * p.n);
    if let Some(bias) = bias {
        if bias.dtype() != DType::F32 || (bias.numel() != p.n && !per_entry) {
            return Err(Error::Shape(format!(
                "matmul: bias must be f32 with {} values (or {} x {} for a batch), got {bias:?}",
                p.n, p.batch, p.n
            )));
        }
    }
    check_dtypes(a, b)?;
    check_out(a, b, out, &p.out_shape)?;
    let max = a.gpu().caps().max_workgroup_count;
    let (kernel, groups, splits) = layout(rec, a, b, &p, trans_a, trans_b)?;
    // Every index the kernels form stays below the largest operand, which is bindable and so
    // below 2^32 bytes; check the element counts anyway so an index can never wrap.
    for t in [a, b, out] {
        if t.numel() > u32::MAX as usize {
            return Err(Error::too_large(Limit::Index, format!("matmul: {t:?} has more than 2^32 elements")));
        }
    }
    let params = Params::of(&p, trans_a, trans_b, accumulate);
    let params = Params { flags: params.flags | cpu_flags(kernel, &p, trans_a, trans_b), ..params };
    if splits > 1 {
        let grid = [groups[0] as u32, groups[1] as u32];
        split_k_into(rec, kernel, grid, [a, b, out], &p, params, splits, accumulate)?;
        return add_bias(rec, out, bias);
    }
    // The bias binding: the bias itself, or any buffer when there is none (nothing reads it).
    // Only the narrow-side kernel reads a bias per batch entry.
    let fused = bias
        .filter(|_| kernel.takes_bias() && (!per_entry || kernel.is(MATMUL_ROWS_MAIN) || kernel.is_cpu()));
    let bias_flags = match (fused.is_some(), per_entry) {
        (false, _) => 0,
        (true, false) => MATMUL_FLAG_BIAS,
        (true, true) => MATMUL_FLAG_BIAS | MATMUL_FLAG_BIAS_PER_ENTRY,
    };
    let params = Params { flags: params.flags | bias_flags, ..params };
    let tensors = [a, b, out, fused.unwrap_or(b)];
    // Batches beyond the device's z limit go in several dispatches.
    let z_max = max[2] as usize;
    let mut base = 0;
    while base < groups[2] {
        let count = (groups[2] - base).min(z_max);
        let chunk = [groups[0] as u32, groups[1] as u32, count as u32];
        kernel.dispatch(rec, chunk, tensors, &Params { batch_base: base as u32, ..params })?;
        base += count;
    }
    if fused.is_none() {
        add_bias(rec, out, bias)?;
    }
    Ok(())
}

/// The kernel a product of plan `p` runs on in this recording, its workgroups and the pieces K
/// is cut into (1: none).
fn layout(
    rec: &Recorder,
    a: &Tensor,
    b: &Tensor,
    p: &Plan,
    trans_a: bool,
    trans_b: bool,
) -> Result<(MatmulKernel, [usize; 3], usize)> {
    let kernel = choose_kernel(a, b, p, trans_a, trans_b, rec);
    let groups = grid(a.gpu(), kernel, p, if p.m == 0 || p.n == 0 { 0 } else { p.batch })?;
    // The CPU kernel has tiles enough for a CPU's threads, and K pieces would break its
    // multiples of 4.
    let splits = if kernel.is_cpu() { 1 } else { split_k(p.batch, groups[0] * groups[1], p.k) };
    Ok((kernel, groups, splits))
}

/// The kernel `op(a) @ op(b)` runs on in `rec`, and the pieces K is cut into where it is: what a
/// benchmark row names (`matmul_coop_rows128_cols64_frag_cols2::main, K in 39 pieces`).
pub fn product_kernel(
    rec: &Recorder,
    a: &Tensor,
    b: &Tensor,
    trans_a: bool,
    trans_b: bool,
) -> Result<String> {
    let p = plan(a.shape(), b.shape(), trans_a, trans_b)?;
    check_dtypes(a, b)?;
    let (kernel, _, splits) = layout(rec, a, b, &p, trans_a, trans_b)?;
    let name = match kernel {
        MatmulKernel::Tiled(k) => k.name(),
        MatmulKernel::Coop(k) => k.name(),
    };
    Ok(if splits > 1 { format!("{name}, K in {splits} pieces") } else { name })
}

/// `out += bias` along its rows, for the kernels that cannot add it themselves.
fn add_bias(rec: &mut Recorder, out: &Tensor, bias: Option<&Tensor>) -> Result<()> {
    match bias {
        Some(bias) if out.numel() > 0 => {
            // [n] for every row, or [batch, 1, n] for each entry's rows.
            let n = *out.shape().last().expect("a matrix");
            let shape = if bias.numel() == n { vec![n] } else { vec![bias.numel() / n, 1, n] };
            binary_into(rec, out, &bias.reshape(&shape)?, out, Binary::Add)
        }
        _ => Ok(()),
    }
}

/// Workgroups a product should have at least: a few per compute unit of a large GPU.
const SPLIT_TARGET_GROUPS: usize = 256;
/// The shortest stretch of K one workgroup of a split product sums.
const SPLIT_MIN_K: usize = 256;
/// Most partial products of a split.
const SPLIT_MAX: usize = 64;

/// How many pieces to cut K into: a product with few output tiles and a long K (the weight
/// gradient `x^T dy` over thousands of rows is 1 tile of 128x128 with K in the thousands)
/// would leave all but a few workgroups of the device idle while each walks all of K. 1 means
/// no split.
fn split_k(batch: usize, tiles: usize, k: usize) -> usize {
    if batch != 1 || tiles == 0 || tiles >= SPLIT_TARGET_GROUPS {
        return 1;
    }
    (SPLIT_TARGET_GROUPS / tiles).min(k / SPLIT_MIN_K).clamp(1, SPLIT_MAX)
}

/// A product split along K: piece z of `chunk = K / splits` (a multiple of 8 on the
/// cooperative-matrix kernels; the last piece also takes the remainder, in a second dispatch)
/// is a batch entry whose operands start z * chunk along K, written to its own slice of a
/// `[pieces, M, N]` buffer; the pieces are then summed into `out` (added to it when
/// accumulating).
#[allow(clippy::too_many_arguments)]
fn split_k_into(
    rec: &mut Recorder,
    kernel: MatmulKernel,
    [gx, gy]: [u32; 2],
    [a, b, out]: [&Tensor; 3],
    p: &Plan,
    params: Params,
    splits: usize,
    accumulate: bool,
) -> Result<()> {
    // The cooperative-matrix kernels read 8 halves at a time from offsets that are multiples
    // of 8: their pieces start at multiples of 8 along K.
    let chunk = match kernel {
        MatmulKernel::Coop(_) => p.k / splits / 8 * 8,
        MatmulKernel::Tiled(_) => p.k / splits,
    };
    let rem = p.k - chunk * splits;
    let pieces = splits + (rem > 0) as usize;
    let partial = Tensor::empty(a.gpu(), &[pieces, p.m, p.n], DType::F32)?;
    let split = Params {
        k: chunk as u32,
        accumulate: 0,
        // Along K, a moves by a_col and b by b_row.
        a_batch: chunk as u32 * params.a_col,
        b_batch: chunk as u32 * params.b_row,
        ..params
    };
    // The kernels' bias binding is unused here (flags bit 2 clear): b stands in.
    kernel.dispatch(rec, [gx, gy, splits as u32], [a, b, &partial, b], &split)?;
    if rem > 0 {
        let tail = Params { k: rem as u32, batch_base: splits as u32, ..split };
        kernel.dispatch(rec, [gx, gy, 1], [a, b, &partial, b], &tail)?;
    }
    reduce_into(rec, &partial, 0, Reduce::Sum, out, accumulate)
}

/// The kernel for one product of `a` and `b` in `rec` (which says how narrow f32 products and
/// large cooperative ones are to be tiled).
fn choose_kernel(
    a: &Tensor,
    b: &Tensor,
    p: &Plan,
    trans_a: bool,
    trans_b: bool,
    rec: &Recorder,
) -> MatmulKernel {
    let gpu = a.gpu();
    let narrow_choice = rec.narrow_matmul();
    if a.dtype() == DType::F32 {
        let vec4 = match narrow_choice {
            NarrowMatmul::Device => gpu.caps().cpu_kernels,
            NarrowMatmul::Vec4 => true,
            NarrowMatmul::Rows | NarrowMatmul::Tiles => false,
        };
        let k = cpu_kernel(p, trans_a, trans_b);
        // It reads both operands through texel buffers.
        let texel = a.texel_bindable() && b.texel_bindable();
        if vec4 && texel && cpu_kernel_fits(gpu.caps()) && gpu.supports(k) {
            return MatmulKernel::Tiled(k);
        }
        let narrow = p.m.min(p.n);
        let rows = match narrow_choice {
            NarrowMatmul::Device => gpu.caps().cpu_kernels,
            NarrowMatmul::Rows | NarrowMatmul::Vec4 => true,
            NarrowMatmul::Tiles => false,
        };
        return MatmulKernel::Tiled(if narrow <= NARROW && rows {
            MATMUL_ROWS_MAIN
        } else if narrow <= NARROW_32 {
            MATMUL_SMALL_TS32_MAIN
        } else if narrow <= NARROW {
            MATMUL_SMALL_TS64_MAIN
        } else {
            MATMUL_MAIN
        });
    }
    match coop_kernel_for(gpu.caps(), p.m, p.n, rec.wide_matmul_blocks()) {
        Some(k) if gpu.supports(k) && coop_layout_ok(p, trans_a, trans_b) => MatmulKernel::Coop(k),
        _ => MatmulKernel::Tiled(MATMUL_MAIN_F16),
    }
}

/// The CPU kernel's variant for a product: which operand it reads in vec4s along which axis
/// (`shaders/matmul_cpu.wgsl`'s LAYOUT; tensors start on a storage offset alignment, at least 16
/// bytes, and bind whole vec4s). Every shape and layout has one; [`cpu_flags`] says which
/// operands it reads one value at a time.
/// Its output tile is 8 rows by 32, 64 or 128 columns, the narrowest that holds N up to 128.
fn cpu_kernel(p: &Plan, trans_a: bool, trans_b: bool) -> TiledKernel {
    let layout = if trans_a && p.m.is_multiple_of(4) {
        1
    } else if !trans_a && trans_b && p.k.is_multiple_of(4) {
        2
    } else {
        0
    };
    let cols = match p.n {
        0..=32 => 0,
        33..=64 => 1,
        _ => 2,
    };
    CPU_KERNELS[layout][cols]
}

/// The flags of the CPU kernel's scalar paths for a product (0 for other kernels): A or B read
/// one value at a time where its variant cannot read it in vec4s.
fn cpu_flags(kernel: MatmulKernel, p: &Plan, trans_a: bool, trans_b: bool) -> u32 {
    let a_vec4 = !trans_a && p.k.is_multiple_of(4);
    let b_vec4 = !trans_b && p.n.is_multiple_of(4);
    let scalar = |vec4: bool, flag: u32| if vec4 { 0 } else { flag };
    match kernel.cpu_layout() {
        Some((0, _)) => scalar(a_vec4, MATMUL_FLAG_A_SCALAR) | scalar(b_vec4, MATMUL_FLAG_B_SCALAR),
        Some((1, _)) => scalar(b_vec4, MATMUL_FLAG_B_SCALAR),
        _ => 0,
    }
}

/// Whether the CPU kernel's workgroup of 8 lanes lies within one subgroup on this device (its
/// broadcasts read the other lanes of the subgroup).
fn cpu_kernel_fits(caps: &Caps) -> bool {
    caps.min_subgroup_size >= 8
}

fn check_dtypes(a: &Tensor, b: &Tensor) -> Result<()> {
    match (a.dtype(), b.dtype()) {
        (DType::F32, DType::F32) | (DType::F16, DType::F16) => Ok(()),
        (x, y) if x == y => {
            Err(Error::DType(format!("matmul: operands must be f32 or f16, got {}", x.name())))
        }
        (x, y) => Err(Error::DType(format!(
            "matmul: operand dtypes differ (a is {}, b is {}); convert one first",
            x.name(),
            y.name()
        ))),
    }
}

/// Plain f64 loops, the definition the kernels are tested against.
pub mod reference {
    use super::plan;
    use crate::error::Result;

    /// `op(a) @ op(b)` for row-major `a` and `b` of the given shapes (see [`super::plan`]);
    /// returns the output and its shape.
    pub fn matmul(
        a: &[f64],
        a_shape: &[usize],
        b: &[f64],
        b_shape: &[usize],
        trans_a: bool,
        trans_b: bool,
    ) -> Result<(Vec<f64>, Vec<usize>)> {
        let p = plan(a_shape, b_shape, trans_a, trans_b)?;
        let (m, n, k) = (p.m, p.n, p.k);
        let mut out = vec![0.0; p.batch * m * n];
        for z in 0..p.batch {
            let a0 = z * p.a_batch_stride;
            let b0 = z * p.b_batch_stride;
            for i in 0..m {
                for j in 0..n {
                    let mut sum = 0.0;
                    for kk in 0..k {
                        let x = if trans_a { a[a0 + kk * m + i] } else { a[a0 + i * k + kk] };
                        let y = if trans_b { b[b0 + j * k + kk] } else { b[b0 + kk * n + j] };
                        sum += x * y;
                    }
                    out[(z * m + i) * n + j] = sum;
                }
            }
        }
        Ok((out, p.out_shape))
    }
}
