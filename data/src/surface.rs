//! A triangle mesh from points sampled on a surface (the surface decoder's samples of a frame).
//!
//! 1. The points' cells in a grid of `resolution` cells along the longest side of their box
//!    (less their stray 0.1 % on each side), each occupied cell grown by the samples' spacing
//!    (1 to 4 cells) to close the gaps between them;
//! 2. everything the grid's boundary reaches through empty cells is outside; the rest (the
//!    grown shell and what it encloses) is inside: a closed surface becomes a solid, an open one
//!    (cloth) a thin shell;
//! 3. the inside's indicator, blurred by a 3 x 3 x 3 box, is contoured at 1/2 by surface nets:
//!    a vertex in every cell of the sample grid the level crosses (the mean of its edges'
//!    crossings), and a quad (two triangles) for every crossed grid edge, joining the four
//!    cells around it and facing out of the inside;
//! 4. each vertex moves along the contour's normal to the mean of the samples within the
//!    growth and 2 cells of it (it stays where it is when there are none), which takes away the
//!    growth and puts the surface on the samples; then 10 rounds of Taubin's smoothing take
//!    their noise out, and pieces of less than 1 % of the triangles (the shells of stray
//!    samples) are dropped.
//!
//! The mesh is watertight where the samples enclose a volume; its detail is a cell. Tests:
//! [`tests`] (a sphere's area, volume, distance from the samples and Euler characteristic; a
//! torus's genus), `tools/tests` (the command).

use crate::{DataError, DataResult};

pub use velox_io::mesh::Mesh;

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The most cells a sample's cell grows by.
const MAX_GROWTH: usize = 4;

/// Cells along the box's longest side that [`mesh_of_points`] takes.
pub const RESOLUTIONS: std::ops::RangeInclusive<usize> = 8..=256;

/// The grid: cells per axis, the corner of cell 0 and a cell's side.
struct Grid {
    n: [usize; 3],
    origin: [f64; 3],
    cell: f64,
}

impl Grid {
    fn index(&self, c: [usize; 3]) -> usize {
        (c[2] * self.n[1] + c[1]) * self.n[0] + c[0]
    }
    fn len(&self) -> usize {
        self.n[0] * self.n[1] * self.n[2]
    }
    /// The cell holding `p`, clamped to the grid.
    fn cell_of(&self, p: [f64; 3]) -> [usize; 3] {
        std::array::from_fn(|a| {
            (((p[a] - self.origin[a]) / self.cell).floor().max(0.0) as usize).min(self.n[a] - 1)
        })
    }
    /// The centre of cell `c` (where the sample of the field sits).
    fn centre(&self, c: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|a| self.origin[a] + (c[a] + 0.5) * self.cell)
    }
}

/// The mesh of the surface the points `xyz` (`[N * 3]`) sample, on a grid of `resolution`
/// cells along their longest side (see the module docs).
pub fn mesh_of_points(xyz: &[f32], resolution: usize) -> DataResult<Mesh> {
    if !RESOLUTIONS.contains(&resolution) {
        return Err(DataError::Invalid(format!(
            "a mesh resolution of {resolution} cells: give {} to {}",
            RESOLUTIONS.start(),
            RESOLUTIONS.end()
        )));
    }
    if !xyz.len().is_multiple_of(3) || xyz.len() < 12 {
        return Err(DataError::Invalid(format!("{} values are not 4 or more points of x, y, z", xyz.len())));
    }
    if let Some(i) = xyz.iter().position(|v| !v.is_finite()) {
        return Err(DataError::Invalid(format!("point {}: coordinate {} is not finite", i / 3, xyz[i])));
    }
    let all: Vec<[f64; 3]> = xyz.chunks_exact(3).map(|p| [p[0], p[1], p[2]].map(f64::from)).collect();
    // The box of the samples but their stray 0.1 % on each side (a decoder's outliers would
    // otherwise stretch the grid), 2 % wider; samples outside it are left out.
    let (mut lo, mut hi) = ([0.0; 3], [0.0; 3]);
    for a in 0..3 {
        let mut v: Vec<f64> = all.iter().map(|p| p[a]).collect();
        v.sort_by(f64::total_cmp);
        let cut = v.len() / 1000;
        let (l, h) = (v[cut], v[v.len() - 1 - cut]);
        (lo[a], hi[a]) = (l - 0.02 * (h - l), h + 0.02 * (h - l));
    }
    let points: Vec<[f64; 3]> =
        all.into_iter().filter(|p| (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a])).collect();
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    if extent <= 0.0 {
        return Err(DataError::Invalid("the points are all at one place: they span no surface".into()));
    }
    let cell = extent / resolution as f64;
    // How far each sample's cell grows: past the samples' spacing, which the area of the cells
    // they occupy gives (about 1.5 cell areas each), so that a sparse sampling still closes.
    let occupied_cells = {
        let mut c: Vec<[i64; 3]> =
            points.iter().map(|p| std::array::from_fn(|a| ((p[a] - lo[a]) / cell).floor() as i64)).collect();
        c.sort_unstable();
        c.dedup();
        c.len()
    };
    let spacing = (1.5 * occupied_cells as f64 / points.len() as f64).sqrt();
    let grow = (spacing.ceil() as usize).clamp(1, MAX_GROWTH);
    let margin = grow + 2;
    let n = std::array::from_fn(|a| ((hi[a] - lo[a]) / cell).ceil() as usize + 1 + 2 * margin);
    let origin = std::array::from_fn(|a| lo[a] - margin as f64 * cell);
    let grid = Grid { n, origin, cell };

    // 1. Occupied cells, grown; the points listed by cell for step 4.
    let coords: Vec<[usize; 3]> = points.iter().map(|p| grid.cell_of(*p)).collect();
    let cells: Vec<usize> = coords.iter().map(|&c| grid.index(c)).collect();
    let mut occupied = vec![false; grid.len()];
    let side = 2 * grow + 1;
    for c in &coords {
        for dz in 0..side {
            for dy in 0..side {
                for dx in 0..side {
                    let d = [dx, dy, dz];
                    let q: [usize; 3] =
                        std::array::from_fn(|a| (c[a] + d[a]).saturating_sub(grow).min(n[a] - 1));
                    occupied[grid.index(q)] = true;
                }
            }
        }
    }
    let mut start = vec![0u32; grid.len() + 1];
    for &c in &cells {
        start[c + 1] += 1;
    }
    for i in 0..grid.len() {
        start[i + 1] += start[i];
    }
    let mut fill = start.clone();
    let mut by_cell = vec![0u32; points.len()];
    for (i, &c) in cells.iter().enumerate() {
        by_cell[fill[c] as usize] = i as u32;
        fill[c] += 1;
    }

    // 2. The outside: the empty cells the boundary reaches.
    let mut outside = vec![false; grid.len()];
    let mut stack = Vec::new();
    for z in 0..n[2] {
        for y in 0..n[1] {
            for x in 0..n[0] {
                let on_boundary =
                    x == 0 || y == 0 || z == 0 || x == n[0] - 1 || y == n[1] - 1 || z == n[2] - 1;
                let i = grid.index([x, y, z]);
                if on_boundary && !occupied[i] && !outside[i] {
                    outside[i] = true;
                    stack.push([x, y, z]);
                }
            }
        }
    }
    while let Some(c) = stack.pop() {
        for a in 0..3 {
            for step in [-1i64, 1] {
                let v = c[a] as i64 + step;
                if v < 0 || v >= n[a] as i64 {
                    continue;
                }
                let mut q = c;
                q[a] = v as usize;
                let i = grid.index(q);
                if !occupied[i] && !outside[i] {
                    outside[i] = true;
                    stack.push(q);
                }
            }
        }
    }

    // 3. The blurred inside, contoured at 1/2.
    let inside: Vec<f32> = outside.iter().map(|&o| if o { 0.0 } else { 1.0 }).collect();
    let field = blur(&inside, n);
    let level = 0.5f32;
    let value = |c: [usize; 3]| field[grid.index(c)];
    let cubes = [n[0] - 1, n[1] - 1, n[2] - 1];
    let cube_index = |c: [usize; 3]| (c[2] * cubes[1] + c[1]) * cubes[0] + c[0];
    let mut vertex_of = vec![u32::MAX; cubes[0] * cubes[1] * cubes[2]];
    let mut positions: Vec<[f64; 3]> = Vec::new();
    const CORNERS: [[usize; 3]; 8] =
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]];
    const EDGES: [(usize, usize); 12] =
        [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)];
    for z in 0..cubes[2] {
        for y in 0..cubes[1] {
            for x in 0..cubes[0] {
                let corner = CORNERS.map(|d| value([x + d[0], y + d[1], z + d[2]]));
                let above = corner.iter().filter(|&&v| v > level).count();
                if above == 0 || above == 8 {
                    continue;
                }
                let mut sum = [0.0f64; 3];
                let mut crossings = 0.0;
                for (a, b) in EDGES {
                    let (va, vb) = (corner[a], corner[b]);
                    if (va > level) == (vb > level) {
                        continue;
                    }
                    let t = ((level - va) / (vb - va)) as f64;
                    for k in 0..3 {
                        sum[k] += CORNERS[a][k] as f64 + t * (CORNERS[b][k] as f64 - CORNERS[a][k] as f64);
                    }
                    crossings += 1.0;
                }
                let local = sum.map(|s| s / crossings);
                vertex_of[cube_index([x, y, z])] = positions.len() as u32;
                positions.push(grid.centre([x as f64 + local[0], y as f64 + local[1], z as f64 + local[2]]));
            }
        }
    }
    // A quad for every crossed edge of the sample grid, facing out of the inside: around the
    // edge along axis a, its four cubes in the order that turns positively about +a.
    let mut triangles = Vec::new();
    for z in 1..n[2] - 1 {
        for y in 1..n[1] - 1 {
            for x in 1..n[0] - 1 {
                let v0 = value([x, y, z]) > level;
                for a in 0..3 {
                    let mut e = [x, y, z];
                    e[a] += 1;
                    if v0 == (value(e) > level) {
                        continue;
                    }
                    let quad: [[usize; 3]; 4] = match a {
                        0 => [[x, y - 1, z - 1], [x, y, z - 1], [x, y, z], [x, y - 1, z]],
                        1 => [[x - 1, y, z - 1], [x - 1, y, z], [x, y, z], [x, y, z - 1]],
                        _ => [[x - 1, y - 1, z], [x, y - 1, z], [x, y, z], [x - 1, y, z]],
                    };
                    let mut q = quad.map(|c| vertex_of[cube_index(c)]);
                    if q.contains(&u32::MAX) {
                        continue;
                    }
                    // Inside at the edge's start: the outside lies along +a, as the order faces.
                    if !v0 {
                        q.reverse();
                    }
                    triangles.push([q[0], q[1], q[2]]);
                    triangles.push([q[0], q[2], q[3]]);
                }
            }
        }
    }

    // 4. Onto the samples, along the contour's normals, then smoothed.
    let contour = Mesh { positions: positions.iter().map(|p| p.map(|v| v as f32)).collect(), triangles };
    let normals = contour.normals();
    let reach = (grow + 2) as f64 * cell;
    let span = grow as i64 + 3;
    let mut snapped: Vec<[f64; 3]> = positions
        .iter()
        .zip(&normals)
        .map(|(&p, nrm)| {
            let c = grid.cell_of(p);
            let mut sum = [0.0f64; 3];
            let mut count = 0usize;
            for dz in -span..=span {
                for dy in -span..=span {
                    for dx in -span..=span {
                        let d = [dx, dy, dz];
                        let q: [i64; 3] = std::array::from_fn(|a| c[a] as i64 + d[a]);
                        if (0..3).any(|a| q[a] < 0 || q[a] >= n[a] as i64) {
                            continue;
                        }
                        let i = grid.index(q.map(|v| v as usize));
                        for &k in &by_cell[start[i] as usize..start[i + 1] as usize] {
                            let s = points[k as usize];
                            let d = sub(s, p);
                            if dot(d, d) <= reach * reach {
                                for a in 0..3 {
                                    sum[a] += s[a];
                                }
                                count += 1;
                            }
                        }
                    }
                }
            }
            if count == 0 {
                return p;
            }
            let towards = sub(sum.map(|s| s / count as f64), p);
            let nrm = nrm.map(f64::from);
            let along = dot(towards, nrm);
            std::array::from_fn(|a| p[a] + along * nrm[a])
        })
        .collect();
    taubin(&mut snapped, &contour.triangles, SMOOTHING);
    let mesh = Mesh {
        positions: snapped.iter().map(|p| p.map(|v| v as f32)).collect(),
        triangles: contour.triangles,
    };
    Ok(without_specks(mesh))
}

/// Pieces of the mesh smaller than this share of its triangles are dropped.
const SPECK: f64 = 0.01;

/// The mesh without its pieces (triangles joined through shared vertices) of fewer than
/// [`SPECK`] of its triangles: the shells of stray samples.
fn without_specks(m: Mesh) -> Mesh {
    let mut parent: Vec<u32> = (0..m.positions.len() as u32).collect();
    fn root(parent: &mut [u32], mut i: u32) -> u32 {
        while parent[i as usize] != i {
            parent[i as usize] = parent[parent[i as usize] as usize];
            i = parent[i as usize];
        }
        i
    }
    for t in &m.triangles {
        for k in 1..3 {
            let (a, b) = (root(&mut parent, t[0]), root(&mut parent, t[k]));
            parent[a.max(b) as usize] = a.min(b);
        }
    }
    let mut size = vec![0usize; m.positions.len()];
    for t in &m.triangles {
        size[root(&mut parent, t[0]) as usize] += 1;
    }
    let least = (SPECK * m.triangles.len() as f64).ceil() as usize;
    let kept: Vec<[u32; 3]> =
        m.triangles.iter().copied().filter(|t| size[root(&mut parent, t[0]) as usize] >= least).collect();
    let mut index = vec![u32::MAX; m.positions.len()];
    let mut positions = Vec::new();
    let triangles = kept
        .iter()
        .map(|t| {
            t.map(|v| {
                if index[v as usize] == u32::MAX {
                    index[v as usize] = positions.len() as u32;
                    positions.push(m.positions[v as usize]);
                }
                index[v as usize]
            })
        })
        .collect();
    Mesh { positions, triangles }
}

/// Rounds of Taubin smoothing after the snap.
const SMOOTHING: usize = 10;

/// Taubin's smoothing (a shrinking step of 0.5 towards the neighbours' mean, then a growing
/// one of -0.53), `rounds` times: takes the noise of the samples out of the surface without
/// shrinking it as plain averaging does.
fn taubin(positions: &mut [[f64; 3]], triangles: &[[u32; 3]], rounds: usize) {
    let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); positions.len()];
    for t in triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            neighbours[a as usize].push(b);
            neighbours[b as usize].push(a);
        }
    }
    for list in &mut neighbours {
        list.sort_unstable();
        list.dedup();
    }
    for _ in 0..rounds {
        for factor in [0.5, -0.53] {
            let before = positions.to_vec();
            for (p, list) in positions.iter_mut().zip(&neighbours) {
                if list.is_empty() {
                    continue;
                }
                let mut mean = [0.0; 3];
                for &q in list {
                    for a in 0..3 {
                        mean[a] += before[q as usize][a];
                    }
                }
                for a in 0..3 {
                    p[a] += factor * (mean[a] / list.len() as f64 - p[a]);
                }
            }
        }
    }
}

/// The field blurred by a 3 x 3 x 3 box (one axis at a time; the grid's edge repeats).
fn blur(field: &[f32], n: [usize; 3]) -> Vec<f32> {
    let mut out = field.to_vec();
    let stride = [1, n[0], n[0] * n[1]];
    for a in 0..3 {
        let src = out.clone();
        for (i, v) in out.iter_mut().enumerate() {
            let c = (i / stride[a]) % n[a];
            let lo = if c > 0 { i - stride[a] } else { i };
            let hi = if c + 1 < n[a] { i + stride[a] } else { i };
            *v = (src[lo] + src[i] + src[hi]) / 3.0;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;
    use velox_engine::rng::Rng;

    /// Points drawn uniformly on a sphere of radius `r` about `centre`.
    fn sphere(count: usize, r: f64, centre: [f64; 3], seed: u64) -> Vec<f32> {
        let mut rng = Rng::new(seed);
        (0..count)
            .flat_map(|_| {
                let v = [rng.normal(), rng.normal(), rng.normal()];
                let l = dot(v, v).sqrt();
                (0..3).map(move |a| (centre[a] + r * v[a] / l) as f32)
            })
            .collect()
    }

    /// Vertices - edges + faces, and whether every edge joins exactly two triangles that run
    /// it in opposite directions (a closed, consistently oriented surface).
    fn euler_and_closed(m: &Mesh) -> (i64, bool) {
        let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
        for t in &m.triangles {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        let closed = directed.iter().all(|(&(a, b), &c)| c == 1 && directed.get(&(b, a)) == Some(&1));
        let edges = directed.len() / 2;
        (m.positions.len() as i64 - edges as i64 + m.triangles.len() as i64, closed)
    }

    #[test]
    fn a_sampled_sphere_becomes_a_closed_sphere_on_its_samples() {
        let (r, centre) = (0.6, [0.1, -0.2, 0.3]);
        let m = mesh_of_points(&sphere(30_000, r, centre, 3), 48).unwrap();
        let (euler, closed) = euler_and_closed(&m);
        assert!(closed, "every edge between two triangles, oriented alike");
        assert_eq!(euler, 2, "a sphere's Euler characteristic");
        let cell = 2.0 * r / 48.0;
        for p in &m.positions {
            let d = dot(sub(p.map(f64::from), centre), sub(p.map(f64::from), centre)).sqrt();
            assert!((d - r).abs() < 0.25 * cell, "a vertex {d} from the centre, the radius {r}");
        }
        let (area, volume) = m.area_and_volume();
        let (want_area, want_volume) =
            (4.0 * std::f64::consts::PI * r * r, 4.0 / 3.0 * std::f64::consts::PI * r.powi(3));
        assert!((area / want_area - 1.0).abs() < 0.05, "area {area}, the sphere's {want_area}");
        assert!(
            (volume / want_volume - 1.0).abs() < 0.05,
            "volume {volume} (facing out), the sphere's {want_volume}"
        );
        // The normals point away from the centre.
        for (p, nrm) in m.positions.iter().zip(m.normals()) {
            let out = sub(p.map(f64::from), centre);
            assert!(dot(out, nrm.map(f64::from)) > 0.0);
        }
    }

    #[test]
    fn a_torus_keeps_its_hole() {
        let mut rng = Rng::new(5);
        let (big, small) = (0.6, 0.22);
        let xyz: Vec<f32> = (0..40_000)
            .flat_map(|_| {
                let (u, v) = (rng.uniform() * std::f64::consts::TAU, rng.uniform() * std::f64::consts::TAU);
                let ring = big + small * v.cos();
                [ring * u.cos(), ring * u.sin(), small * v.sin()].map(|c| c as f32)
            })
            .collect();
        let m = mesh_of_points(&xyz, 64).unwrap();
        let (euler, closed) = euler_and_closed(&m);
        assert!(closed);
        assert_eq!(euler, 0, "a torus: genus 1");
        assert!(m.area_and_volume().1 > 0.0);
    }

    #[test]
    fn bad_points_are_refused_by_name() {
        let e = |xyz: &[f32], r| mesh_of_points(xyz, r).unwrap_err().to_string();
        let ok = sphere(100, 0.5, [0.0; 3], 1);
        assert!(e(&ok, 4).contains("resolution of 4"));
        assert!(e(&ok[..10], 32).contains("not 4 or more points"));
        let mut nan = ok.clone();
        nan[7] = f32::NAN;
        assert!(e(&nan, 32).contains("point 2"));
        assert!(e(&[0.5; 30], 32).contains("all at one place"));
    }
}
