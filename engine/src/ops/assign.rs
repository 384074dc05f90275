//! Nearest-query assignment in 4D for the encoder's localized cross-attention (docs/models.md,
//! Encoder: every input point belongs to the cell of its nearest query). Kernels:
//! `shaders/assign.wgsl`.
//!
//! Points are f32 `[N, 4]` and queries f32 `[k, 4]`, rows `(x, y, z, tau * time_scale)`
//! (validate host data with [`crate::ops::window::validate_points`]). The distance is the
//! squared Euclidean distance in f32, `dot(p - q, p - q)`; ties go to the lower query index.
//!
//! [`assign_nearest`] gives the cell (query index) of every point, u32 `[N]`.
//! [`assign_grouped`] also sorts the points by cell, giving [`Cells`]:
//! - `cells`: u32 `[N]`, the nearest query of each point;
//! - `order`: u32 `[N]`, point indices sorted by cell, ascending point index within a cell;
//! - `sorted_cells`: u32 `[N]`, `cells[order[i]]`;
//! - `offsets`: u32 `[k + 1]`, cell `c` holds `order[offsets[c]..offsets[c + 1]]`, for every
//!   query (an empty cell has `offsets[c] == offsets[c + 1]`), `offsets[k] = N`.
//!
//! That is the layout the per-cell cross-attention takes: query `c` attends to its segment, and
//! a query whose segment is empty gets zeros.
//!
//! Tests: the harness's `assign` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/assign.rs` (ties, continuous points, grouped
//! cells, bad input).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::{ASSIGN_CELL_OFFSETS, ASSIGN_NEAREST};
use crate::ops::sort::{self, sort_indices};
use crate::ops::window::{key_bits_for, point_rows};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// Invocations per workgroup and points per invocation of `nearest`; must match `WG` and `PTS`
/// in `shaders/assign.wgsl`.
const NEAREST_WG: u64 = 128;
const NEAREST_PTS: u64 = 4;

use crate::kernels::params::AssignParams as Params;

fn query_rows(queries: &Tensor) -> Result<u32> {
    let k = point_rows(queries, "assign_nearest (queries)")?;
    if k == 0 {
        return Err(Error::Shape("assign_nearest: no queries; there must be at least one".into()));
    }
    Ok(k)
}

/// The index of the nearest query (u32 `[N]`) for every point.
///
/// Cost: brute force, N * k distance evaluations ([`distance_evals`], 11 flops each,
/// [`flops`]); the queries stream through workgroup memory in tiles of 256 and each invocation
/// measures 4 points per query read, so device memory traffic is small. 1.44M points against
/// 8192 queries is 1.2e10 evaluations. On lavapipe (2 cores) 100k points against 2048 queries
/// took 101 ms (2.0e9 evaluations/s, 22 GFLOP/s).
pub fn assign_nearest(rec: &mut Recorder, points: &Tensor, queries: &Tensor) -> Result<Tensor> {
    let n = point_rows(points, "assign_nearest (points)")?;
    let k = query_rows(queries)?;
    let cells = Tensor::empty(points.gpu(), &[n as usize], DType::U32)?;
    let groups = (n as u64).div_ceil(NEAREST_WG * NEAREST_PTS);
    rec.dispatch_linear(
        ASSIGN_NEAREST,
        groups,
        args::AssignNearestArgs { points, queries, cells: &cells },
        &Params { n, k },
    )?;
    Ok(cells)
}

/// Points assigned to their nearest query and grouped by it; the format is in the module
/// header.
pub struct Cells {
    pub cells: Tensor,
    pub order: Tensor,
    pub sorted_cells: Tensor,
    pub offsets: Tensor,
}

/// [`assign_nearest`], then the points sorted by cell with the offsets of all k cells.
///
/// Cost: the assignment, a stable radix sort of N pairs on [`key_bits_for`]`(k)` bits, and one
/// pass over N to place the k + 1 offsets.
pub fn assign_grouped(rec: &mut Recorder, points: &Tensor, queries: &Tensor) -> Result<Cells> {
    let cells = assign_nearest(rec, points, queries)?;
    let k = queries.shape()[0];
    let (order, sorted_cells, offsets) = group_by_cell(rec, &cells, k)?;
    Ok(Cells { cells, order, sorted_cells, offsets })
}

/// Sorts points by cell id (u32 `[N]`, every id below `k`) and returns `(order, sorted_cells,
/// offsets)` as in [`Cells`], with offsets for all `k` cells.
pub fn group_by_cell(rec: &mut Recorder, cells: &Tensor, k: usize) -> Result<(Tensor, Tensor, Tensor)> {
    if cells.dtype() != DType::U32 || cells.shape().len() != 1 {
        return Err(Error::Shape(format!("group_by_cell: cells must be u32 [N], got {cells:?}")));
    }
    if k == 0 || k >= 1 << 31 {
        return Err(Error::Shape(format!("group_by_cell: {k} cells, must be in 1..2^31")));
    }
    let n = fit_u32(cells.numel(), || format!("group_by_cell: {cells:?} has 2^32 elements or more"))?;
    let gpu = cells.gpu().clone();
    let (sorted_cells, order) = sort_indices(rec, cells, key_bits_for(k as u64))?;
    let offsets = Tensor::empty(&gpu, &[k + 1], DType::U32)?;
    let params = Params { n, k: k as u32 };
    rec.dispatch_linear(
        ASSIGN_CELL_OFFSETS,
        (n as u64 + 1).div_ceil(256),
        args::AssignCellOffsetsArgs { sorted_cells: &sorted_cells, offsets: &offsets },
        &params,
    )?;
    Ok((order, sorted_cells, offsets))
}

/// Distance evaluations of [`assign_nearest`]: N * k.
pub fn distance_evals(n: usize, k: usize) -> u64 {
    n as u64 * k as u64
}

/// Flops of [`assign_nearest`] (for TFLOP/s in benchmarks): 4 subtractions, 4 multiplications
/// and 3 additions per distance; the comparison is not counted.
pub fn flops(n: usize, k: usize) -> u64 {
    11 * distance_evals(n, k)
}

/// Bytes [`group_by_cell`] reads and writes on `gpu` for `n` points and `k` cells.
pub fn group_bytes(gpu: &crate::Gpu, n: usize, k: usize) -> u64 {
    sort::bytes_moved(gpu, n, key_bits_for(k as u64)) + 4 * (2 * n as u64 + k as u64 + 1)
}

/// The CPU versions the kernels are checked against.
pub mod reference {
    /// Squared distance between two rows in f64.
    pub fn dist2(a: &[f32], b: &[f32]) -> f64 {
        a.iter().zip(b).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum()
    }

    /// Nearest query of every point by f64 squared distance, ties to the lower index.
    pub fn assign_nearest(points: &[f32], queries: &[f32]) -> Vec<u32> {
        points
            .chunks_exact(4)
            .map(|p| {
                let mut best = (f64::INFINITY, 0u32);
                for (j, q) in queries.chunks_exact(4).enumerate() {
                    let d = dist2(p, q);
                    if d < best.0 {
                        best = (d, j as u32);
                    }
                }
                best.1
            })
            .collect()
    }

    /// `(order, offsets)`: point indices stably sorted by cell, and the k + 1 cell offsets.
    pub fn group_by_cell(cells: &[u32], k: usize) -> (Vec<u32>, Vec<u32>) {
        let mut order: Vec<u32> = (0..cells.len() as u32).collect();
        order.sort_by_key(|&i| cells[i as usize]);
        let mut offsets = vec![0u32; k + 1];
        for &c in cells {
            offsets[c as usize + 1] += 1;
        }
        for c in 0..k {
            offsets[c + 1] += offsets[c];
        }
        (order, offsets)
    }
}
