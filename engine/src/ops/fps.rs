//! Farthest point sampling in 4D: how the encoder picks its k queries (docs/models.md, Encoder:
//! 4k points at random, then FPS down to k). Kernel: `shaders/fps.wgsl`.
//!
//! Points are f32 `[N, 4]` rows `(x, y, z, tau * time_scale)` (validate host data with
//! [`crate::ops::window::validate_points`]). The candidates are indices into the points, chosen
//! by the caller or by [`random_candidates`] with the seeded [`Rng`]. FPS starts from
//! **candidate 0** (so with random candidates the start is random too), and each step adds the
//! candidate whose squared distance (f32) to the chosen set is largest, ties to the lower
//! candidate position. The output is u32 `[k]`: the chosen **point** indices (not candidate
//! positions), in the order chosen. Repeated candidate indices are allowed: each copy counts
//! once, so duplicates are chosen only after every distinct point is at distance 0.
//!
//! Tests: the harness's `fps` row (`engine/tests/ops/cases.rs`: forward against the f64 reference
//! at awkward shapes); `engine/tests/ops/assign.rs` (exact choices on clusters, spheres and ties,
//! candidates).

use crate::device::Gpu;
use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::params::FpsOrderParams;
use crate::kernels::{Kernel, FPS_ORDER_MAIN, FPS_WG1024_MAIN, FPS_WG256_MAIN};
use crate::ops::gather::gather;
use crate::ops::sort::sort_pairs;
use crate::ops::window::point_rows;
use crate::recorder::Recorder;
use crate::rng::Rng;
use crate::tensor::{DType, Tensor};
use crate::{fit_u32, Limit};

/// The two sizes of the one workgroup (`@variants WG` in `shaders/fps.wgsl`), and which runs
/// where: see [`variant`].
pub const WG_GPU: u32 = 1024;
pub const WG_CPU: u32 = 256;
/// Candidates per query that [`sample_queries`] draws (docs/models.md: 4k).
pub const OVERSAMPLE: usize = 4;

use crate::kernels::params::FpsParams as Params;

/// `min(m, n)` distinct indices in `0..n`, uniformly at random and in random order (a partial
/// Fisher-Yates shuffle that stores only the swapped entries, so it costs O(m), not O(n)).
pub fn random_candidates(n: usize, m: usize, rng: &mut Rng) -> Result<Vec<u32>> {
    let n32 = fit_u32(n, || format!("random_candidates: {n} points"))?;
    let m = m.min(n);
    let mut swapped = std::collections::HashMap::with_capacity(2 * m);
    let mut out = Vec::with_capacity(m);
    for i in 0..m as u32 {
        let j = i + rng.below(n32 - i);
        let at_j = *swapped.get(&j).unwrap_or(&j);
        let at_i = *swapped.get(&i).unwrap_or(&i);
        swapped.insert(j, at_i);
        out.push(at_j);
    }
    Ok(out)
}

/// Chooses `k` of the `candidates` (indices into `points`, f32 `[N, 4]`) by farthest point
/// sampling and returns their point indices, u32 `[k]`. `k = 0` gives an empty tensor.
///
/// Cost: the candidates are first put in 4D Morton order (one small dispatch for the codes, a
/// 32-bit radix sort of m pairs, a gather), then one dispatch of one workgroup (its size from
/// [`variant`]) runs the k - 1 iterations. Each invocation owns a run of sorted candidates and
/// their bounding box, and an iteration measures only the runs whose box is near enough to the
/// new point to lower a distance (the rest are skipped exactly: see `shaders/fps.wgsl`); then a
/// subgroup argmax and one barrier. At 8192 of 32768 points on a moving sphere, 16 of 1024
/// invocations measure their runs in an average iteration. [`flops`] and [`bytes_moved`] count
/// the unskipped work, an upper bound. It runs on one compute unit, so it is latency-bound on a
/// large GPU. On lavapipe (2 cores, Mesa 25), 8192 of 32768 took 1790 ms before the skipping
/// and 202 ms after.
pub fn fps(rec: &mut Recorder, points: &Tensor, candidates: &[u32], k: usize) -> Result<Tensor> {
    let (kernel, _) = variant(points.gpu());
    fps_with(rec, kernel, points, candidates, k)
}

/// [`fps`] with a chosen workgroup size, [`WG_CPU`] or [`WG_GPU`] (for tests: both must give
/// the same choices on every device).
pub fn fps_with_workgroup(
    rec: &mut Recorder,
    wg: u32,
    points: &Tensor,
    candidates: &[u32],
    k: usize,
) -> Result<Tensor> {
    let kernel = match wg {
        WG_CPU => FPS_WG256_MAIN,
        WG_GPU => FPS_WG1024_MAIN,
        _ => {
            return Err(Error::Invalid(format!(
                "fps: workgroup of {wg}; the kernels have {WG_CPU} and {WG_GPU}"
            )))
        }
    };
    fps_with(rec, kernel, points, candidates, k)
}

fn fps_with(
    rec: &mut Recorder,
    kernel: Kernel<Params, args::FpsWg256MainArgs<'static>>,
    points: &Tensor,
    candidates: &[u32],
    k: usize,
) -> Result<Tensor> {
    let n = point_rows(points, "fps")?;
    let m = candidates.len();
    if k > m {
        return Err(Error::Invalid(format!("fps: cannot choose k = {k} from {m} candidates")));
    }
    if m >= 1 << 30 {
        return Err(Error::too_large(Limit::Index, format!("fps: {m} candidates, at most 2^30 - 1")));
    }
    if let Some((pos, &c)) = candidates.iter().enumerate().find(|(_, &c)| c >= n) {
        return Err(Error::Invalid(format!("fps: candidate {pos} is point {c}, but there are {n} points")));
    }
    let gpu = points.gpu();
    let out = Tensor::empty(gpu, &[k], DType::U32)?;
    if k == 0 {
        return Ok(out);
    }
    let index = Tensor::from_slice(gpu, &[m], candidates)?;
    let cands = gather(rec, points, &index)?;
    let params = Params { m: m as u32, k: k as u32 };
    let codes = Tensor::empty(gpu, &[m], DType::U32)?;
    let iota = Tensor::empty(gpu, &[m], DType::U32)?;
    let order = FpsOrderParams { m: params.m, k: params.k };
    rec.dispatch(
        FPS_ORDER_MAIN,
        [1, 1, 1],
        args::FpsOrderMainArgs { cands: &cands, codes: &codes, iota: &iota },
        &order,
    )?;
    let (_, perm) = sort_pairs(rec, &codes, &iota, 32)?;
    let sorted = gather(rec, &cands, &perm)?;
    let min_dist = Tensor::empty(gpu, &[m], DType::F32)?;
    let args = args::FpsWg256MainArgs {
        cands: &sorted,
        perm: &perm,
        cand_index: &index,
        min_dist: &min_dist,
        chosen: &out,
    };
    rec.dispatch(kernel, [1, 1, 1], args, &params)?;
    Ok(out)
}

/// The FPS kernel for this device and its description (for `velox info`). The iterations'
/// cost differs by kind of device:
/// - on a GPU it is the latency of an iteration: a barrier, and the loads of the few
///   invocations near the new point, one slot after another. 1024 invocations keep those runs
///   short (32 slots each at 32768 candidates);
/// - on a CPU (lavapipe) every invocation costs time at every iteration, skipping or not:
///   8192 of 32768 took 591 ms with 1024 invocations, 202 ms with 256 and 271 ms with 64.
///
/// A device whose limits the 1024-invocation kernel does not fit (fewer invocations per
/// workgroup, or less workgroup memory than its 24 KiB) gets 256 (every Vulkan device allows
/// 128 invocations and 16 KiB; the engine's other kernels already need 256).
pub fn variant(gpu: &Gpu) -> (Kernel<Params, args::FpsWg256MainArgs<'static>>, String) {
    let caps = gpu.caps();
    let wg = if caps.cpu_kernels || !gpu.supports(FPS_WG1024_MAIN) { WG_CPU } else { WG_GPU };
    let kernel = if wg == WG_GPU { FPS_WG1024_MAIN } else { FPS_WG256_MAIN };
    let slots = |m: u32| m.div_ceil(wg);
    (
        kernel,
        format!(
            "{wg} invocations, Morton-ordered runs of candidates ({} each at 32768), box culling",
            slots(32768)
        ),
    )
}

/// The encoder's queries: `OVERSAMPLE * k` random candidates (all points when there are fewer),
/// then [`fps`] down to `k`. Fails when `k` is 0 or more than the number of points.
pub fn sample_queries(rec: &mut Recorder, points: &Tensor, k: usize, rng: &mut Rng) -> Result<Tensor> {
    let n = point_rows(points, "sample_queries")? as usize;
    if k == 0 || k > n {
        return Err(Error::Invalid(format!(
            "sample_queries: k = {k} queries from {n} points; need 1 <= k <= N"
        )));
    }
    let candidates = random_candidates(n, k.saturating_mul(OVERSAMPLE), rng)?;
    fps(rec, points, &candidates, k)
}

/// Flops of [`fps`] (for benchmarks): per iteration and candidate, a 4D squared distance (11)
/// and a min.
pub fn flops(m: usize, k: usize) -> u64 {
    12 * m as u64 * k.saturating_sub(1) as u64
}

/// Bytes of device memory [`fps`] touches: per iteration and candidate, 16 bytes of coordinates
/// and the running distance read and written (8), mostly from cache on a large GPU.
pub fn bytes_moved(m: usize, k: usize) -> u64 {
    24 * m as u64 * k.saturating_sub(1) as u64
}

/// The CPU version the kernel is checked against.
pub mod reference {
    use crate::ops::assign::reference::dist2;

    /// FPS in f64 with the kernel's rules: start at candidate 0, the largest distance to the
    /// chosen set next, ties to the lower position, each position chosen at most once.
    pub fn fps(points: &[f32], candidates: &[u32], k: usize) -> Vec<u32> {
        let row = |c: u32| &points[4 * c as usize..4 * c as usize + 4];
        let mut min_dist = vec![f64::INFINITY; candidates.len()];
        let mut out = Vec::with_capacity(k);
        let mut current = 0usize;
        for it in 0..k {
            out.push(candidates[current]);
            if it + 1 == k {
                break;
            }
            min_dist[current] = -1.0;
            let c = row(candidates[current]);
            let mut best = (-2.0, 0usize);
            for (j, &cj) in candidates.iter().enumerate() {
                if min_dist[j] >= 0.0 {
                    min_dist[j] = min_dist[j].min(dist2(row(cj), c));
                }
                if min_dist[j] > best.0 {
                    best = (min_dist[j], j);
                }
            }
            current = best.1;
        }
        out
    }
}
