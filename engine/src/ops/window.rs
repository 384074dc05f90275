//! 4D voxel windows for the encoder's localized self-attention (docs/models.md, Encoder), and the
//! grouping of points into one variable-length segment per occupied window. Kernels:
//! `shaders/window.wgsl`.
//!
//! **Points** are f32 `[N, 4]` rows `(x, y, z, tau * time_scale)`, built by the caller from the
//! 7-channel cloud. NaN or Inf coordinates must be rejected before upload with
//! [`validate_points`]; the kernels never index out of range on them but their windows are
//! meaningless.
//!
//! **Window ids** ([`window_ids`]): a [`WindowGrid`] has an origin, a cell width and a number of
//! cells per axis. Along each axis the cell is `floor((p - origin) * inv_cell)` computed in f32
//! with `inv_cell = 1 / cell` rounded to f32 once on the host, so a point exactly on a border
//! belongs to the cell above it (cells are half-open `[origin + c w, origin + (c + 1) w)` up to
//! that rounding). Points outside the grid, the upper bound included, are clamped to the border
//! cell. The id is the row-major index of `(cx, cy, cz, ct)` over the cell counts, t fastest:
//! `((cx * ny + cy) * nz + cz) * nt + ct`, a u32 in `0..num_windows`. [`WindowGrid::shifted`]
//! gives the shifted windows of alternate layers: origin moved down by half a cell and one more
//! cell per axis, so the shifted grid covers the same bounds.
//!
//! **Window groups** ([`group_by_window`]): the points sorted stably by window id, and the occupied
//! windows as a compact list. With `S` occupied windows and `C = min(num_windows, N)` (the
//! most there can be), the outputs are
//! - `order`: u32 `[N]`, point indices sorted by window id, ascending point index within a
//!   window (the radix sort is stable);
//! - `sorted_ids`: u32 `[N]`, `ids[order[i]]`;
//! - `offsets`: u32 `[C + 1]`; segment `s < S` holds `order[offsets[s]..offsets[s + 1]]`, and
//!   `offsets[S..=C]` are all `N`, so reading past the segment count gives empty segments;
//! - `segment_ids`: u32 `[C]`, the window id of each segment, ascending, `u32::MAX` past `S`;
//! - `count`: u32 `[1]` holding `S`, on the device (the host reads it only if it must).
//!
//! This is the layout variable-length segment attention takes: tokens gathered by `order`,
//! segment bounds `offsets[..=S]`. Empty windows cost nothing.
//!
//! Tests: the harness's `window` row (`engine/tests/ops/cases.rs`: forward against the f64
//! reference at awkward shapes); `engine/tests/ops/assign.rs` (grid geometry, border cells,
//! grouping).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::{WINDOW_HEADS, WINDOW_SEGMENTS, WINDOW_WINDOW_IDS};
use crate::ops::fill::fill_bits;
use crate::ops::scan::{self, exclusive_scan};
use crate::ops::sort::{self, sort_indices};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};
use crate::{fit_u32, Limit};

/// Invocations per workgroup of every kernel in `shaders/window.wgsl`.
const WG: u64 = 256;

/// A regular 4D grid of windows over `(x, y, z, tau * time_scale)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WindowGrid {
    /// Lower corner of cell (0, 0, 0, 0).
    pub origin: [f32; 4],
    /// Cell width per axis (positive).
    pub cell: [f32; 4],
    /// Number of cells per axis (at least 1).
    pub cells: [u32; 4],
}

impl WindowGrid {
    /// The grid of cells of width `cell` that covers `[lo, hi]` on every axis, starting at `lo`.
    /// An axis gets `ceil((hi - lo) / cell)` cells (at least one), where a ratio within 1e-6
    /// of a whole number counts as that number: `[-1, 1]` in cells of 0.5 is 4 cells, and so is
    /// 24 frames in cells of 6 frames.
    pub fn new(lo: [f32; 4], hi: [f32; 4], cell: [f32; 4]) -> Result<WindowGrid> {
        let mut cells = [0u32; 4];
        for a in 0..4 {
            let (l, h, w) = (lo[a] as f64, hi[a] as f64, cell[a] as f64);
            if !(l.is_finite() && h.is_finite() && w.is_finite()) || w <= 0.0 || h < l {
                return Err(Error::Invalid(format!(
                    "window grid axis {a}: bounds [{l}, {h}] with cell width {w}; the bounds must be \
                     finite with lo <= hi and the width positive"
                )));
            }
            let ratio = (h - l) / w;
            let count = (ratio - 1e-6).ceil().max(1.0);
            if count > u32::MAX as f64 {
                return Err(Error::too_large(Limit::Index, format!("window grid axis {a}: {ratio} cells")));
            }
            cells[a] = count as u32;
        }
        WindowGrid { origin: lo, cell, cells }.checked()
    }

    /// The shifted grid: origin moved down by half a cell on every axis, one more cell per axis.
    pub fn shifted(&self) -> WindowGrid {
        WindowGrid {
            origin: std::array::from_fn(|a| self.origin[a] - 0.5 * self.cell[a]),
            cell: self.cell,
            cells: self.cells.map(|c| c.saturating_add(1)),
        }
    }

    /// Number of windows (product of the cell counts; `u64::MAX` if that overflows).
    pub fn num_windows(&self) -> u64 {
        self.cells.iter().fold(1u64, |acc, &c| acc.saturating_mul(c as u64))
    }

    /// `1 / cell` rounded to f32: what the kernel and the reference multiply by.
    pub fn inv_cell(&self) -> [f32; 4] {
        self.cell.map(|w| 1.0 / w)
    }

    /// Fails unless the grid is usable: positive finite widths, finite origin, at least one
    /// cell per axis, at most 2^32 windows (ids are u32).
    pub fn checked(self) -> Result<WindowGrid> {
        let ok_axis = |a: usize| {
            self.origin[a].is_finite()
                && self.cell[a].is_finite()
                && self.cell[a] > 0.0
                && self.inv_cell()[a].is_finite()
                && self.cells[a] >= 1
        };
        if let Some(a) = (0..4).find(|&a| !ok_axis(a)) {
            return Err(Error::Invalid(format!(
                "window grid axis {a}: origin {}, cell width {}, {} cells; the origin and width must \
                 be finite, the width positive, and there must be at least one cell",
                self.origin[a], self.cell[a], self.cells[a]
            )));
        }
        if self.num_windows() > 1u64 << 32 {
            return Err(Error::too_large(
                Limit::Index,
                format!(
                    "window grid {:?} has {} windows; ids are u32, so at most 2^32",
                    self.cells,
                    self.num_windows()
                ),
            ));
        }
        Ok(self)
    }
}

use crate::kernels::params::WindowParams as Params;

impl Params {
    fn count(n: u32) -> Params {
        Params { origin: [0.0; 4], inv_cell: [0.0; 4], cells: [1; 4], n, capacity: 0, _pad1: 0, _pad2: 0 }
    }
}

/// Checks host point data laid out as `[N, 4]` rows and returns N. The first row with a NaN or
/// infinite coordinate is named in a [`Error::Invalid`].
pub fn validate_points(data: &[f32]) -> Result<usize> {
    if !data.len().is_multiple_of(4) {
        return Err(Error::Shape(format!(
            "points: {} values is not a whole number of (x, y, z, t) rows of 4",
            data.len()
        )));
    }
    if let Some((row, p)) = data.chunks_exact(4).enumerate().find(|(_, p)| p.iter().any(|v| !v.is_finite())) {
        return Err(Error::Invalid(format!(
            "point {row} is ({}, {}, {}, {}): every coordinate must be finite (no NaN or Inf)",
            p[0], p[1], p[2], p[3]
        )));
    }
    Ok(data.len() / 4)
}

/// Checks that `points` is an f32 `[N, 4]` tensor whose element indices fit the kernels' u32
/// arithmetic, and returns N.
pub(crate) fn point_rows(points: &Tensor, op: &str) -> Result<u32> {
    if points.dtype() != DType::F32 || points.shape().len() != 2 || points.shape()[1] != 4 {
        return Err(Error::Shape(format!("{op}: points must be f32 [N, 4] (x, y, z, t), got {points:?}")));
    }
    let n = points.shape()[0];
    if n >= 1 << 30 {
        return Err(Error::too_large(Limit::Index, format!("{op}: {n} points, at most 2^30 - 1")));
    }
    Ok(n as u32)
}

/// The window id (u32 `[N]`) of every point of `points` (f32 `[N, 4]`) in `grid`.
///
/// Cost: one pass, 20 bytes per point ([`window_ids_bytes`]).
pub fn window_ids(rec: &mut Recorder, points: &Tensor, grid: &WindowGrid) -> Result<Tensor> {
    let n = point_rows(points, "window_ids")?;
    let grid = grid.checked()?;
    let ids = Tensor::empty(points.gpu(), &[n as usize], DType::U32)?;
    let params = Params {
        origin: grid.origin,
        inv_cell: grid.inv_cell(),
        cells: grid.cells,
        n,
        capacity: 0,
        _pad1: 0,
        _pad2: 0,
    };
    rec.dispatch_linear(
        WINDOW_WINDOW_IDS,
        (n as u64).div_ceil(WG),
        args::WindowWindowIdsArgs { points, ids: &ids },
        &params,
    )?;
    Ok(ids)
}

/// Bits that hold every id below `num_ids` (at least 1): how far the radix sort must go.
pub fn key_bits_for(num_ids: u64) -> u32 {
    (64 - num_ids.saturating_sub(1).leading_zeros()).clamp(1, 32)
}

/// Points grouped into one segment per occupied window; the format is in the module header.
pub struct WindowGroups {
    pub order: Tensor,
    pub sorted_ids: Tensor,
    pub offsets: Tensor,
    pub segment_ids: Tensor,
    pub count: Tensor,
}

impl WindowGroups {
    /// Reads the segment count back (waits for nothing: call after the recording is submitted).
    /// For attention over the windows, gather the tokens by `order` and use `offsets` as both
    /// the query and the key offsets of [`crate::ops::attention::Segments`].
    pub fn read_count(&self) -> Result<u32> {
        Ok(self.count.read::<u32>()?[0])
    }
}

/// Sorts the points by window id and lists the occupied windows (format in the module header).
/// `ids` is u32 `[N]` with every id below `num_windows` (as [`window_ids`] gives).
///
/// Cost: a stable radix sort of N keys and their indices on [`key_bits_for`]`(num_windows)`
/// bits, plus two passes over N and one scan of N ([`group_bytes`]).
pub fn group_by_window(rec: &mut Recorder, ids: &Tensor, num_windows: u64) -> Result<WindowGroups> {
    if ids.dtype() != DType::U32 || ids.shape().len() != 1 {
        return Err(Error::Shape(format!("group_by_window: ids must be u32 [N], got {ids:?}")));
    }
    if num_windows == 0 || num_windows > 1u64 << 32 {
        return Err(Error::Shape(format!("group_by_window: {num_windows} windows, must be in 1..=2^32")));
    }
    let n = fit_u32(ids.numel(), || format!("group_by_window: {ids:?} has 2^32 elements or more"))?;
    let gpu = ids.gpu().clone();
    let capacity = num_windows.min(n as u64) as usize;
    let offsets = Tensor::empty(&gpu, &[capacity + 1], DType::U32)?;
    let segment_ids = Tensor::empty(&gpu, &[capacity], DType::U32)?;
    if n == 0 {
        // No points: no invocation of `segments` to write the one offset.
        fill_bits(rec, &offsets, 0)?;
    }
    let (sorted_ids, order) = sort_indices(rec, ids, key_bits_for(num_windows))?;
    let flags = Tensor::empty(&gpu, &[n as usize], DType::U32)?;
    let positions = Tensor::empty(&gpu, &[n as usize], DType::U32)?;
    let groups = (n as u64).div_ceil(WG);
    rec.dispatch_linear(
        WINDOW_HEADS,
        groups,
        args::WindowHeadsArgs { sorted_ids: &sorted_ids, flags: &flags },
        &Params::count(n),
    )?;
    let count = exclusive_scan(rec, &flags, &positions)?;
    let fit = u32::try_from(capacity).expect("at most n");
    rec.dispatch_linear(
        WINDOW_SEGMENTS,
        groups,
        args::WindowSegmentsArgs {
            sorted_ids: &sorted_ids,
            flags: &flags,
            positions: &positions,
            offsets: &offsets,
            segment_ids: &segment_ids,
        },
        &Params { capacity: fit, ..Params::count(n) },
    )?;
    Ok(WindowGroups { order, sorted_ids, offsets, segment_ids, count })
}

/// Bytes [`window_ids`] reads and writes for `n` points (for GB/s in benchmarks).
pub fn window_ids_bytes(n: usize) -> u64 {
    20 * n as u64
}

/// Bytes [`group_by_window`] reads and writes on `gpu` for `n` points in `num_windows` windows:
/// the sort, the scan, and the heads and segments passes.
pub fn group_bytes(gpu: &crate::Gpu, n: usize, num_windows: u64) -> u64 {
    let capacity = num_windows.min(n as u64);
    sort::bytes_moved(gpu, n, key_bits_for(num_windows))
        + scan::bytes_moved(n)
        + 4 * (5 * n as u64 + 2 * capacity)
}

/// The CPU versions the kernels are checked against.
pub mod reference {
    use super::WindowGrid;

    /// Cell of one coordinate: the kernel's f32 expression, clamped to the grid.
    pub fn axis_cell(v: f32, origin: f32, inv_cell: f32, cells: u32) -> u32 {
        let c = ((v - origin) * inv_cell).floor();
        c.clamp(0.0, (cells - 1) as f32) as u32
    }

    /// Window id of every `[N, 4]` row.
    pub fn window_ids(points: &[f32], grid: &WindowGrid) -> Vec<u32> {
        let inv = grid.inv_cell();
        let n = grid.cells;
        points
            .chunks_exact(4)
            .map(|p| {
                let c: [u32; 4] = std::array::from_fn(|a| axis_cell(p[a], grid.origin[a], inv[a], n[a]));
                ((c[0] * n[1] + c[1]) * n[2] + c[2]) * n[3] + c[3]
            })
            .collect()
    }

    /// `(order, offsets[..=S], segment_ids[..S])`: a stable sort of point indices by id and the
    /// bounds and ids of the runs of equal ids.
    pub fn group_by_window(ids: &[u32]) -> (Vec<u32>, Vec<u32>, Vec<u32>) {
        let mut order: Vec<u32> = (0..ids.len() as u32).collect();
        order.sort_by_key(|&i| ids[i as usize]);
        let mut offsets = Vec::new();
        let mut segment_ids = Vec::new();
        for (i, &p) in order.iter().enumerate() {
            let id = ids[p as usize];
            if segment_ids.last() != Some(&id) {
                offsets.push(i as u32);
                segment_ids.push(id);
            }
        }
        offsets.push(ids.len() as u32);
        (order, offsets, segment_ids)
    }
}
