//! Cloth simulation by extended position-based dynamics (XPBD, Macklin, Mueller and Chentanez
//! 2016). Kernels: `shaders/cloth.wgsl`.
//!
//! A frame of `dt` seconds is `substeps` substeps of `h = dt / substeps` (small substeps with one
//! pass over the constraints each are what makes XPBD stiff and stable), each:
//! 1. predict: `v += h g`, `p = x`, `x += h v` (gravity along -y; pinned particles, inverse
//!    mass 0, stay);
//! 2. the distance constraints (stretch along every edge, bending across every interior edge),
//!    one colour at a time ([`colour`]: no two constraints of a colour share a particle), with
//!    their XPBD multipliers zeroed at the substep's start;
//! 3. self-collision: particles are sorted by hashed grid cell and each is pushed away from the
//!    particles within `2 radius` of it, half the overlap each (particles within `exclude` of
//!    each other in the rest shape are mesh neighbours and never collide);
//! 4. the ground `y = ground`: lifted onto it, sideways travel cut by friction, upward speed
//!    `restitution` times the downward one, and `v = (x - p) / h`.
//!
//! Every step is a fixed sequence of dispatches with no atomics, so the same input gives the
//! same bits on a device. [`reference`] runs the same substep in f64 on the CPU.
//!
//! Tests: the harness's `cloth` row (`engine/tests/ops/cases.rs`: positions after 16 substeps
//! against the reference, sheets of 4 to 289 particles); `tests/data/cloth.rs` (velocities
//! too, free fall, rest lengths, each parameter by construction and by effect, layers that do
//! not pass through each other, a thousand random drops, the same bits again).

use crate::error::{Error, Result};
use crate::fit_u32;
use crate::kernels::args;
use crate::kernels::{
    CLOTH_APPLY, CLOTH_CELL_BOUNDS, CLOTH_COLLIDE, CLOTH_DISTANCE, CLOTH_GROUND, CLOTH_HASH_KEYS,
    CLOTH_PREDICT,
};
use crate::ops::fill::{fill, fill_bits};
use crate::ops::sort::sort_pairs;
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};
use crate::Gpu;

/// How the cloth moves.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClothParams {
    /// Gravity along -y, in scene units per second squared.
    pub gravity: f32,
    /// Height of the ground plane.
    pub ground: f32,
    /// Friction: sideways travel in contact is cut by this times the depth lifted.
    pub friction: f32,
    /// Upward speed after a contact over downward speed before it (0: no bounce).
    pub restitution: f32,
    /// Particle radius: the cloth rests this far above the ground, and particles stay twice
    /// this apart.
    pub radius: f32,
    /// Particles closer than this in the rest shape never collide with each other.
    pub exclude: f32,
    pub substeps: usize,
    /// Self-collision on or off.
    pub collide: bool,
    /// Velocity damping per second (air drag): `v *= 1 - damping h` each substep.
    pub damping: f32,
}

impl Default for ClothParams {
    fn default() -> Self {
        ClothParams {
            gravity: 9.81,
            ground: -1.0,
            friction: 0.5,
            restitution: 0.0,
            radius: 0.01,
            exclude: 0.03,
            substeps: 20,
            collide: true,
            damping: 0.5,
        }
    }
}

impl ClothParams {
    fn check(&self) -> Result<()> {
        let ok = |v: f32, lo: f32, hi: f32| v.is_finite() && v >= lo && v <= hi;
        if !(ok(self.gravity, -1e3, 1e3)
            && ok(self.ground, -1e3, 1e3)
            && ok(self.friction, 0.0, 1e3)
            && ok(self.restitution, 0.0, 1.0)
            && ok(self.radius, 1e-6, 1.0)
            && ok(self.exclude, 0.0, 10.0)
            && ok(self.damping, 0.0, 1e3)
            && (1..=10_000).contains(&self.substeps))
        {
            return Err(Error::Invalid(format!("cloth: parameters out of range: {self:?}")));
        }
        Ok(())
    }
}

/// A distance constraint between particles `a` and `b`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Constraint {
    pub a: u32,
    pub b: u32,
    pub rest: f32,
    /// Inverse stiffness (0: rigid).
    pub compliance: f32,
}

/// The particles and constraints of a cloth.
#[derive(Clone, Debug, Default)]
pub struct ClothMesh {
    pub positions: Vec<[f32; 3]>,
    pub inv_mass: Vec<f32>,
    pub constraints: Vec<Constraint>,
    /// Each particle's place in the rest shape (the flat pattern) for the collision exclusion.
    pub rest_positions: Vec<[f32; 3]>,
}

impl ClothMesh {
    /// The triangles of a square sheet of `side` x `side` particles numbered row by row: two a
    /// cell, wound alike (for [`ClothMesh::from_triangles`]).
    pub fn grid_triangles(side: usize) -> Vec<[u32; 3]> {
        let w = side as u32;
        let cells = (0..w.saturating_sub(1)).flat_map(|r| (0..w - 1).map(move |q| r * w + q));
        cells.flat_map(|a| [[a, a + 1, a + w], [a + 1, a + w + 1, a + w]]).collect()
    }

    /// A mesh of `triangles` over `positions` (the rest shape too): a stretch constraint on
    /// every edge (compliance `stretch`) and a bending one between the opposite corners of
    /// the two triangles of every interior edge (compliance `bend`); every particle of mass 1.
    pub fn from_triangles(
        positions: Vec<[f32; 3]>,
        triangles: &[[u32; 3]],
        stretch: f32,
        bend: f32,
    ) -> Result<ClothMesh> {
        let n = positions.len();
        if let Some(t) = triangles.iter().find(|t| t.iter().any(|&v| v as usize >= n)) {
            return Err(Error::Invalid(format!("cloth: triangle {t:?} names a particle past {n}")));
        }
        let mut edges: std::collections::BTreeMap<(u32, u32), Vec<u32>> = Default::default();
        for t in triangles {
            for k in 0..3 {
                let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
                edges.entry((a.min(b), a.max(b))).or_default().push(c);
            }
        }
        let dist = |a: u32, b: u32| {
            let (p, q) = (positions[a as usize], positions[b as usize]);
            ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
        };
        let mut constraints = Vec::new();
        for (&(a, b), opposite) in &edges {
            constraints.push(Constraint { a, b, rest: dist(a, b), compliance: stretch });
            if let [c, d] = opposite[..] {
                constraints.push(Constraint { a: c, b: d, rest: dist(c, d), compliance: bend });
            }
        }
        let mesh =
            ClothMesh { inv_mass: vec![1.0; n], rest_positions: positions.clone(), positions, constraints };
        mesh.check()?;
        Ok(mesh)
    }

    /// Fails, naming the first bad value, unless every position is finite, every inverse mass
    /// finite and >= 0, and every constraint joins two different particles of the mesh at a
    /// finite rest length with a finite compliance >= 0.
    pub fn check(&self) -> Result<()> {
        let n = self.positions.len();
        if n == 0 {
            return Err(Error::Invalid("cloth: no particles".into()));
        }
        if self.inv_mass.len() != n || self.rest_positions.len() != n {
            return Err(Error::Invalid(format!(
                "cloth: {n} particles, {} inverse masses and {} rest positions",
                self.inv_mass.len(),
                self.rest_positions.len()
            )));
        }
        if let Some(i) =
            self.positions.iter().chain(&self.rest_positions).position(|p| p.iter().any(|v| !v.is_finite()))
        {
            return Err(Error::Invalid(format!("cloth: position {} is not finite", i % n)));
        }
        if let Some(i) = self.inv_mass.iter().position(|w| !(w.is_finite() && *w >= 0.0)) {
            return Err(Error::Invalid(format!("cloth: particle {i} has inverse mass {}", self.inv_mass[i])));
        }
        for (k, c) in self.constraints.iter().enumerate() {
            let bad = c.a as usize >= n
                || c.b as usize >= n
                || c.a == c.b
                || !(c.rest.is_finite() && c.rest >= 0.0)
                || !(c.compliance.is_finite() && c.compliance >= 0.0);
            if bad {
                return Err(Error::Invalid(format!(
                    "cloth: constraint {k} ({c:?}) is not valid for {n} particles"
                )));
            }
        }
        Ok(())
    }
}

/// The constraints reordered into colours (greedy, in order: each goes to the first colour
/// that has neither of its particles), and each colour's `(start, count)`.
pub fn colour(constraints: &[Constraint], particles: usize) -> (Vec<Constraint>, Vec<(usize, usize)>) {
    let mut used: Vec<Vec<bool>> = Vec::new();
    let mut members: Vec<Vec<Constraint>> = Vec::new();
    for c in constraints {
        let (a, b) = (c.a as usize, c.b as usize);
        let k = match used.iter().position(|u| !u[a] && !u[b]) {
            Some(k) => k,
            None => {
                used.push(vec![false; particles]);
                members.push(Vec::new());
                used.len() - 1
            }
        };
        used[k][a] = true;
        used[k][b] = true;
        members[k].push(*c);
    }
    let mut spans = Vec::with_capacity(members.len());
    let mut out = Vec::with_capacity(constraints.len());
    for m in members {
        spans.push((out.len(), m.len()));
        out.extend(m);
    }
    (out, spans)
}

use crate::kernels::params::ClothParams as Params;

/// A cloth on the device; see the module docs.
pub struct ClothSim {
    pub params: ClothParams,
    n: usize,
    x: Tensor,
    p: Tensor,
    v: Tensor,
    w: Tensor,
    pairs: Tensor,
    rest: Tensor,
    compliance: Tensor,
    lambda: Tensor,
    colours: Vec<(usize, usize)>,
    rest_pos: Tensor,
    delta: Tensor,
    /// Each particle's hashed cell and the identity order, the sort's input.
    keys: Tensor,
    order: Tensor,
    cell_start: Tensor,
    cell_end: Tensor,
    table_bits: u32,
}

impl ClothSim {
    /// The mesh at rest (zero velocity) on `gpu`.
    pub fn new(gpu: &Gpu, mesh: &ClothMesh, params: ClothParams) -> Result<ClothSim> {
        mesh.check()?;
        params.check()?;
        let n = mesh.positions.len();
        fit_u32(3 * n, || format!("cloth of {n} particles"))?;
        let (ordered, colours) = colour(&mesh.constraints, n);
        let m = ordered.len().max(1);
        let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
        let mut pairs: Vec<u32> = ordered.iter().flat_map(|c| [c.a, c.b]).collect();
        let mut rest: Vec<f32> = ordered.iter().map(|c| c.rest).collect();
        let mut compliance: Vec<f32> = ordered.iter().map(|c| c.compliance).collect();
        // A mesh without constraints still binds one (unused) of each.
        pairs.resize(2 * m, 0);
        rest.resize(m, 0.0);
        compliance.resize(m, 0.0);
        // A table of about twice the particles, a power of two.
        let table_bits = ((2 * n).next_power_of_two().trailing_zeros()).clamp(4, 24);
        let table = 1usize << table_bits;
        Ok(ClothSim {
            params,
            n,
            x: Tensor::from_slice(gpu, &[n, 3], &flat(&mesh.positions))?,
            p: Tensor::from_slice(gpu, &[n, 3], &flat(&mesh.positions))?,
            v: Tensor::from_slice(gpu, &[n, 3], &vec![0.0f32; 3 * n])?,
            w: Tensor::from_slice(gpu, &[n], &mesh.inv_mass)?,
            pairs: Tensor::from_slice(gpu, &[m, 2], &pairs)?,
            rest: Tensor::from_slice(gpu, &[m], &rest)?,
            compliance: Tensor::from_slice(gpu, &[m], &compliance)?,
            lambda: Tensor::empty(gpu, &[m], DType::F32)?,
            colours,
            rest_pos: Tensor::from_slice(gpu, &[n, 3], &flat(&mesh.rest_positions))?,
            delta: Tensor::empty(gpu, &[n, 3], DType::F32)?,
            keys: Tensor::empty(gpu, &[n], DType::U32)?,
            order: Tensor::empty(gpu, &[n], DType::U32)?,
            cell_start: Tensor::empty(gpu, &[table], DType::U32)?,
            cell_end: Tensor::empty(gpu, &[table], DType::U32)?,
            table_bits,
        })
    }

    pub fn particles(&self) -> usize {
        self.n
    }

    /// The constraints as the device holds them (particles, rest length and compliance read
    /// back from its buffers), in the order they are solved: colour by colour.
    pub fn constraints(&self) -> Result<Vec<Constraint>> {
        let count = self.colours.iter().map(|&(_, c)| c).sum::<usize>();
        let (pairs, rest, compliance) =
            (self.pairs.read::<u32>()?, self.rest.read::<f32>()?, self.compliance.read::<f32>()?);
        Ok((0..count)
            .map(|k| Constraint {
                a: pairs[2 * k],
                b: pairs[2 * k + 1],
                rest: rest[k],
                compliance: compliance[k],
            })
            .collect())
    }

    /// Colours of the constraints (dispatches per substep of the constraint solve).
    pub fn colours(&self) -> usize {
        self.colours.len()
    }

    /// The push constants every kernel of a substep of `dt` seconds reads (the distance
    /// kernel's colour span left at 0): the parameters as the shaders see them.
    pub fn substep_params(&self, dt: f32) -> Params {
        let q = &self.params;
        Params {
            n: self.n as u32,
            start: 0,
            count: 0,
            table: 1 << self.table_bits,
            dt,
            gravity: q.gravity,
            ground: q.ground,
            friction: q.friction,
            restitution: q.restitution,
            radius: q.radius,
            exclude: q.exclude,
            // Cells of 2 r: every particle within reach is in a neighbouring cell.
            cell: 2.0 * q.radius,
            damping: q.damping,
            _pad0: 0,
            _pad1: 0,
            _pad2: 0,
        }
    }

    /// Records one substep of `h` seconds.
    pub fn record_substep(&self, rec: &mut Recorder, h: f32) -> Result<()> {
        let pc = self.substep_params(h);
        let groups = (self.n as u64).div_ceil(256);
        rec.dispatch_linear(
            CLOTH_PREDICT,
            groups,
            args::ClothPredictArgs { x: &self.x, p: &self.p, v: &self.v, w: &self.w },
            &pc,
        )?;
        fill(rec, &self.lambda, 0.0)?;
        for &(start, count) in &self.colours {
            let pc = Params { start: start as u32, count: count as u32, ..pc };
            let args = args::ClothDistanceArgs {
                x: &self.x,
                w: &self.w,
                pairs: &self.pairs,
                rest: &self.rest,
                compliance: &self.compliance,
                lambda: &self.lambda,
            };
            rec.dispatch_linear(CLOTH_DISTANCE, (count as u64).div_ceil(256), args, &pc)?;
        }
        if self.params.collide {
            rec.dispatch_linear(
                CLOTH_HASH_KEYS,
                groups,
                args::ClothHashKeysArgs { x: &self.x, keys: &self.keys, order: &self.order },
                &pc,
            )?;
            let (sorted_keys, sorted_order) = sort_pairs(rec, &self.keys, &self.order, self.table_bits)?;
            fill_bits(rec, &self.cell_start, 0)?;
            fill_bits(rec, &self.cell_end, 0)?;
            rec.dispatch_linear(
                CLOTH_CELL_BOUNDS,
                groups,
                args::ClothCellBoundsArgs {
                    sorted_keys: &sorted_keys,
                    cell_start: &self.cell_start,
                    cell_end: &self.cell_end,
                },
                &pc,
            )?;
            let args = args::ClothCollideArgs {
                x: &self.x,
                w: &self.w,
                sorted_order: &sorted_order,
                cell_start: &self.cell_start,
                cell_end: &self.cell_end,
                rest_pos: &self.rest_pos,
                delta: &self.delta,
            };
            rec.dispatch_linear(CLOTH_COLLIDE, groups, args, &pc)?;
            rec.dispatch_linear(
                CLOTH_APPLY,
                groups,
                args::ClothApplyArgs { x: &self.x, delta: &self.delta },
                &pc,
            )?;
        }
        rec.dispatch_linear(
            CLOTH_GROUND,
            groups,
            args::ClothGroundArgs { x: &self.x, p: &self.p, v: &self.v, w: &self.w },
            &pc,
        )
    }

    /// Advances one frame of `dt` seconds (`substeps` substeps), one submission.
    pub fn step(&mut self, gpu: &Gpu, dt: f32) -> Result<()> {
        if !(dt.is_finite() && dt > 0.0) {
            return Err(Error::Invalid(format!("cloth: a frame of {dt} seconds")));
        }
        let h = dt / self.params.substeps as f32;
        let mut rec = gpu.recorder()?;
        for _ in 0..self.params.substeps {
            self.record_substep(&mut rec, h)?;
        }
        rec.submit()?;
        Ok(())
    }

    /// Overwrites the positions (`[n * 3]`, finite): a hand that carries pinned particles
    /// moves them this way between frames.
    pub fn set_positions(&self, x: &[f32]) -> Result<()> {
        self.check_per_particle("positions", x, 3, |_| true)?;
        self.x.write(x)
    }

    /// Overwrites the velocities (`[n * 3]`, finite): a cloth thrown rather than dropped. Pinned
    /// particles lose theirs at the next substep.
    pub fn set_velocities(&self, v: &[f32]) -> Result<()> {
        self.check_per_particle("velocities", v, 3, |_| true)?;
        self.v.write(v)
    }

    /// Overwrites the inverse masses (`[n]`, finite, >= 0; 0 pins a particle).
    pub fn set_inv_mass(&self, w: &[f32]) -> Result<()> {
        self.check_per_particle("inverse masses", w, 1, |v| v >= 0.0)?;
        self.w.write(w)
    }

    /// Checks that `values` holds `width` values a particle, each finite and passing `ok`; the
    /// error names `what`, and the count or the first bad value and its particle.
    fn check_per_particle(
        &self,
        what: &str,
        values: &[f32],
        width: usize,
        ok: impl Fn(f32) -> bool,
    ) -> Result<()> {
        if values.len() != width * self.n {
            return Err(Error::Invalid(format!(
                "cloth: {} values of {what} for {} particles ({width} a particle)",
                values.len(),
                self.n
            )));
        }
        match values.iter().position(|&v| !(v.is_finite() && ok(v))) {
            Some(i) => {
                Err(Error::Invalid(format!("cloth: {what} of particle {} holds {}", i / width, values[i])))
            }
            None => Ok(()),
        }
    }

    /// Positions, `[n * 3]`.
    pub fn positions(&self) -> Result<Vec<f32>> {
        self.x.read()
    }

    /// Velocities, `[n * 3]`.
    pub fn velocities(&self) -> Result<Vec<f32>> {
        self.v.read()
    }
}

pub mod reference {
    //! The same substep in f64 on the CPU, with the same constraint order; self-collision
    //! looks at every pair (the device's hash finds the same pairs, and sums each particle's
    //! pushes in another order). Plain index loops, as the maths is written.
    #![allow(clippy::needless_range_loop)]

    use super::{colour, ClothMesh, ClothParams};

    pub struct State {
        pub x: Vec<[f64; 3]>,
        pub v: Vec<[f64; 3]>,
    }

    impl State {
        pub fn new(mesh: &ClothMesh) -> State {
            State {
                x: mesh.positions.iter().map(|p| p.map(|v| v as f64)).collect(),
                v: vec![[0.0; 3]; mesh.positions.len()],
            }
        }
    }

    fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
    }

    fn norm(a: [f64; 3]) -> f64 {
        (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
    }

    pub fn substep(s: &mut State, mesh: &ClothMesh, q: &ClothParams, h: f64) {
        let n = s.x.len();
        let w: Vec<f64> = mesh.inv_mass.iter().map(|&w| w as f64).collect();
        let p = s.x.clone();
        for i in 0..n {
            if w[i] > 0.0 {
                s.v[i][1] -= h * q.gravity as f64;
                for a in 0..3 {
                    s.x[i][a] += h * s.v[i][a];
                }
            }
        }
        let (ordered, _) = colour(&mesh.constraints, n);
        for c in &ordered {
            let (a, b) = (c.a as usize, c.b as usize);
            let alpha = c.compliance as f64 / (h * h);
            let denom = w[a] + w[b] + alpha;
            let d = sub(s.x[a], s.x[b]);
            let len = norm(d);
            if denom == 0.0 || len < 1e-12 {
                continue;
            }
            let dl = -(len - c.rest as f64) / denom;
            for k in 0..3 {
                s.x[a][k] += w[a] * dl * d[k] / len;
                s.x[b][k] -= w[b] * dl * d[k] / len;
            }
        }
        if q.collide {
            let reach = 2.0 * q.radius as f64;
            let rest: Vec<[f64; 3]> = mesh.rest_positions.iter().map(|r| r.map(|v| v as f64)).collect();
            let mut delta = vec![[0.0f64; 3]; n];
            for i in 0..n {
                if w[i] == 0.0 {
                    continue;
                }
                for j in 0..n {
                    if j == i || norm(sub(rest[i], rest[j])) < q.exclude as f64 {
                        continue;
                    }
                    let d = sub(s.x[i], s.x[j]);
                    let len = norm(d);
                    if len < reach && len > 1e-9 {
                        for k in 0..3 {
                            delta[i][k] += 0.5 * (reach - len) / len * d[k];
                        }
                    }
                }
            }
            for i in 0..n {
                for k in 0..3 {
                    s.x[i][k] += delta[i][k];
                }
            }
        }
        let floor = q.ground as f64 + q.radius as f64;
        for i in 0..n {
            if w[i] == 0.0 {
                s.v[i] = [0.0; 3];
                continue;
            }
            let mut bounce = None;
            if s.x[i][1] < floor {
                let depth = floor - s.x[i][1];
                let falling = (s.x[i][1] - p[i][1]) / h;
                s.x[i][1] = floor;
                let slide = [s.x[i][0] - p[i][0], s.x[i][2] - p[i][2]];
                let len = (slide[0] * slide[0] + slide[1] * slide[1]).sqrt();
                let keep = if len > 1e-12 { (1.0 - q.friction as f64 * depth / len).max(0.0) } else { 0.0 };
                s.x[i][0] = p[i][0] + keep * slide[0];
                s.x[i][2] = p[i][2] + keep * slide[1];
                bounce = Some(q.restitution as f64 * (-falling).max(0.0));
            }
            let damp = (1.0 - q.damping as f64 * h).max(0.0);
            for k in 0..3 {
                s.v[i][k] = (s.x[i][k] - p[i][k]) / h * damp;
            }
            if let Some(b) = bounce {
                s.v[i][1] = b;
            }
        }
    }
}
