//! Synthetic cloth scenes (the paper's cloth dataset, made with our own solver,
//! `velox_engine::ops::cloth`): a random t-shirt, pair of shorts or towel, folded once or
//! twice by a hand that grabs an edge and carries it over the cloth, lifted to a random height
//! and dropped with zero velocity. The 24 frames of the fall are an [`AnimatedMesh`] like any
//! other scene's, with the simulated centre of mass per frame beside it.
//!
//! Units: a scene unit is half a metre (the [-1, 1]^3 box is a metre across), so gravity is
//! 19.62 units per second squared; frames are the data's 0.01 s apart. Garments are 0.6 to 1.4
//! units across. The simulation runs upright (gravity along -y, the ground y = -0.5); the scene
//! is that world turned [`TILT_DEGREES`] about z, so that the conditioning camera, which the
//! data puts on +x at the height of the origin, looks down on the ground at that angle instead
//! of along it. The record gives the scene's up vector, against gravity.
//!
//! - Patterns: a towel is a rectangle; a t-shirt a body with a neck cut out and two sleeves
//!   sloping down from its shoulders; shorts a waistband over two legs with a gap between them.
//!   Every size and proportion is drawn from the scene's seed. The pattern is cut from a
//!   square grid of [`SPACING`] (a triangle is kept when its three corners are inside), so the
//!   mesh is one layer, with the pattern's coordinates as UVs.
//! - Folds: a line across the cloth is drawn; the particles farthest beyond it (the edge a
//!   hand would grab) are pinned and carried along half circles to their mirror images across
//!   the line, over 30 frames, then released, and the cloth settles for 30 frames; the second
//!   fold the same over another line.
//! - The drop: the folded cloth is lifted 0.2 to 0.6 units, every velocity zero, and falls for
//!   the clip's 24 frames.
//!
//! A scene's seed draws everything (kind, shape, folds, height, yaw, texture), so splits made
//! from disjoint seeds never share a garment shape or a texture.

use velox_engine::ops::cloth::{ClothMesh, ClothParams, ClothSim};
use velox_engine::rng::Rng;
use velox_engine::Gpu;

use crate::mesh::AnimatedMesh;
use crate::procedural::FRAMES;
use crate::texture::{procedural, ImageFolder};
use crate::DataResult;

/// Gravity in scene units (half metres) per second squared.
pub const GRAVITY: f32 = 19.62;
/// Height of the ground plane in the simulation's upright frame.
pub const GROUND: f32 = -0.5;
/// The scene is the simulation's world turned this much about z (its up towards +x).
pub const TILT_DEGREES: f32 = 30.0;
/// Spacing of the pattern grid, in scene units.
pub const SPACING: f32 = 0.04;
/// Seconds between frames (the data's 100 frames per second).
pub const FRAME_DT: f32 = 0.01;
/// Compliance of the garments' stretch constraints (every edge): nearly inextensible.
pub const STRETCH_COMPLIANCE: f32 = 1e-7;
/// Compliance of their bending constraints (across every interior edge): soft, so the cloth
/// folds and drapes.
pub const BEND_COMPLIANCE: f32 = 2e-3;
/// Friction with the ground: sideways travel in contact is cut by this times the depth lifted.
pub const FRICTION: f32 = 0.8;
/// Bounce off the ground: none, cloth lands dead.
pub const RESTITUTION: f32 = 0.0;
/// Air drag, per second.
pub const DAMPING: f32 = 1.0;
/// Particle radius: a quarter of the grid's spacing, so mesh neighbours are never within reach.
pub const RADIUS: f32 = 0.25 * SPACING;
/// Particles within this of each other in the flat pattern never collide: 1.5 spacings, past
/// every edge and diagonal of the grid (the stretch and bending constraints hold those).
pub const EXCLUDE: f32 = 1.5 * SPACING;

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GarmentKind {
    Towel,
    Shirt,
    Shorts,
}

/// A garment's flat pattern: particles in the plane (x, z), triangles, UVs.
#[derive(Clone, Debug)]
pub struct Pattern {
    pub kind: GarmentKind,
    pub points: Vec<[f32; 2]>,
    pub triangles: Vec<[u32; 3]>,
    pub uvs: Vec<[f32; 2]>,
}

/// What made a cloth scene, and its simulated centre of mass per frame.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct ClothRecord {
    pub kind: GarmentKind,
    pub particles: usize,
    pub folds: usize,
    pub drop_height: f32,
    pub gravity: f32,
    /// The ground plane: `dot(x, up) = ground` in the scene.
    pub ground: f32,
    /// The scene's up, against gravity.
    pub up: [f32; 3],
    pub frame_seconds: f32,
    /// The mean of the particles (all of one mass) at each frame, in the scene.
    pub centre_of_mass: Vec<[f32; 3]>,
}

/// The scene's up, against gravity: the upright y turned by [`TILT_DEGREES`] about z.
pub fn up() -> [f32; 3] {
    let t = TILT_DEGREES.to_radians();
    [t.sin(), t.cos(), 0.0]
}

/// A point of the simulation's upright frame in the scene.
fn to_scene(p: [f32; 3]) -> [f32; 3] {
    let t = TILT_DEGREES.to_radians();
    let (s, c) = (t.sin(), t.cos());
    [p[0] * c + p[1] * s, -p[0] * s + p[1] * c, p[2]]
}

fn inside_rect(p: [f32; 2], x0: f32, x1: f32, z0: f32, z1: f32) -> bool {
    p[0] >= x0 && p[0] <= x1 && p[1] >= z0 && p[1] <= z1
}

/// Whether a point of the plane is inside a pattern's outline.
type Inside = Box<dyn Fn([f32; 2]) -> bool>;

/// The inside test of a random pattern of `kind`, and its extent (half width, half depth).
fn outline(kind: GarmentKind, rng: &mut Rng) -> (Inside, [f32; 2]) {
    let r = |rng: &mut Rng, lo: f64, hi: f64| rng.range(lo, hi) as f32;
    match kind {
        GarmentKind::Towel => {
            let (w, d) = (r(rng, 0.35, 0.7), r(rng, 0.25, 0.5));
            (Box::new(move |p| inside_rect(p, -w, w, -d, d)), [w, d])
        }
        GarmentKind::Shirt => {
            // Body from z = -d (hem) to z = d (shoulders); sleeves from the shoulders outward,
            // sloping down (towards the hem) by `slope`; a round neck at the top.
            let (w, d) = (r(rng, 0.28, 0.42), r(rng, 0.32, 0.48));
            let (len, width, slope) = (r(rng, 0.12, 0.3), r(rng, 0.12, 0.2), r(rng, 0.0, 0.6));
            let neck = r(rng, 0.07, 0.11);
            let inside = move |p: [f32; 2]| {
                let body =
                    inside_rect(p, -w, w, -d, d) && (p[0] * p[0] + (p[1] - d) * (p[1] - d)).sqrt() > neck;
                let sleeve = |s: f32| {
                    // Out from the shoulder (0 to len), its top edge sloping down towards the hem.
                    let out = p[0] * s - w;
                    let top = d - slope * out;
                    (0.0..=len).contains(&out) && p[1] <= top && p[1] >= top - width
                };
                body || sleeve(1.0) || sleeve(-1.0)
            };
            let half_width = w + len;
            (Box::new(inside), [half_width, d])
        }
        GarmentKind::Shorts => {
            // Waistband z in [d - band, d]; two legs below it, apart by `gap`, flaring out.
            let (w, d) = (r(rng, 0.28, 0.42), r(rng, 0.25, 0.4));
            let (band, gap, flare) = (r(rng, 0.1, 0.18), r(rng, 0.03, 0.1), r(rng, 0.0, 0.12));
            let inside = move |p: [f32; 2]| {
                let top = inside_rect(p, -w, w, d - band, d);
                // How far below the band, 0 to 1; legs widen outward as they go down.
                let t = ((d - band - p[1]) / (2.0 * d - band)).clamp(0.0, 1.0);
                let outer = w + flare * t;
                let leg = p[1] >= -d && p[1] <= d - band && p[0].abs() >= gap && p[0].abs() <= outer;
                top || leg
            };
            (Box::new(inside), [w + flare, d])
        }
    }
}

/// A random pattern of `kind`: the grid of [`SPACING`] inside its outline, triangulated.
pub fn pattern(kind: GarmentKind, rng: &mut Rng) -> Pattern {
    let (inside, [hw, hd]) = outline(kind, rng);
    let (nx, nz) = ((2.0 * hw / SPACING).ceil() as usize + 1, (2.0 * hd / SPACING).ceil() as usize + 1);
    let at = |i: usize, k: usize| [-hw + i as f32 * SPACING, -hd + k as f32 * SPACING];
    let mut index = vec![u32::MAX; nx * nz];
    let mut points = Vec::new();
    let mut triangles = Vec::new();
    let mut id = |i: usize, k: usize, points: &mut Vec<[f32; 2]>| -> u32 {
        let slot = &mut index[k * nx + i];
        if *slot == u32::MAX {
            *slot = points.len() as u32;
            points.push(at(i, k));
        }
        *slot
    };
    for k in 0..nz - 1 {
        for i in 0..nx - 1 {
            let corners = [(i, k), (i + 1, k), (i, k + 1), (i + 1, k + 1)];
            let ok = corners.map(|(a, b)| inside(at(a, b)));
            for tri in [[0, 1, 2], [1, 3, 2]] {
                if tri.iter().all(|&c| ok[c]) {
                    let t = tri.map(|c| id(corners[c].0, corners[c].1, &mut points));
                    triangles.push(t);
                }
            }
        }
    }
    let extent = 2.0 * hw.max(hd);
    let uvs = points.iter().map(|p| [(p[0] + hw) / extent, (p[1] + hd) / extent]).collect();
    Pattern { kind, points, triangles, uvs }
}

/// How the garments move: the constants above, 20 substeps a frame, self-collision on.
pub fn params() -> ClothParams {
    ClothParams {
        gravity: GRAVITY,
        ground: GROUND,
        friction: FRICTION,
        restitution: RESTITUTION,
        radius: RADIUS,
        exclude: EXCLUDE,
        substeps: 20,
        collide: true,
        damping: DAMPING,
    }
}

/// The solver's mesh of `pat` laid flat on the ground turned `yaw` about the vertical:
/// stretch constraints of [`STRETCH_COMPLIANCE`], bending ones of [`BEND_COMPLIANCE`], the
/// flat pattern as the rest shape of the collision exclusion.
pub fn garment_mesh(pat: &Pattern, yaw: f32) -> DataResult<ClothMesh> {
    let (c, s) = (yaw.cos(), yaw.sin());
    let laid: Vec<[f32; 3]> =
        pat.points.iter().map(|p| [c * p[0] - s * p[1], GROUND + RADIUS, s * p[0] + c * p[1]]).collect();
    let mut mesh = ClothMesh::from_triangles(laid, &pat.triangles, STRETCH_COMPLIANCE, BEND_COMPLIANCE)?;
    mesh.rest_positions = pat.points.iter().map(|p| [p[0], 0.0, p[1]]).collect();
    Ok(mesh)
}

/// Folds the cloth in `sim` over the line through `origin` along `dir` (unit, in xz): the
/// particles beyond 60 % of the farthest one's distance from the line are carried over it.
fn fold(gpu: &Gpu, sim: &mut ClothSim, inv_mass: &[f32], origin: [f32; 2], dir: [f32; 2]) -> DataResult<()> {
    let x = sim.positions()?;
    let side = |i: usize| (x[3 * i] - origin[0]) * -dir[1] + (x[3 * i + 2] - origin[1]) * dir[0];
    let n = x.len() / 3;
    let far = (0..n).map(side).fold(0.0f32, f32::max);
    if far <= 0.0 {
        return Ok(());
    }
    let grabbed: Vec<usize> = (0..n).filter(|&i| side(i) > 0.6 * far).collect();
    let mut w = inv_mass.to_vec();
    for &i in &grabbed {
        w[i] = 0.0;
    }
    sim.set_inv_mass(&w)?;
    let start: Vec<[f32; 3]> = grabbed.iter().map(|&i| [x[3 * i], x[3 * i + 1], x[3 * i + 2]]).collect();
    let carry = 30;
    // The last carried frame lays the edge on the layer below.
    let lift = 2.5 * sim.params.radius;
    for f in 1..=carry {
        let a = std::f32::consts::PI * f as f32 / carry as f32;
        let mut now = sim.positions()?;
        for (&i, s) in grabbed.iter().zip(&start) {
            // Rotate about the fold line: the distance from it swings up and over.
            let d = (s[0] - origin[0]) * -dir[1] + (s[2] - origin[1]) * dir[0];
            let (across, up) = (d * a.cos(), d * a.sin());
            let base = [s[0] - d * -dir[1], s[2] - d * dir[0]];
            now[3 * i] = base[0] + across * -dir[1];
            now[3 * i + 1] = s[1] + up + if f == carry { lift } else { 0.0 };
            now[3 * i + 2] = base[1] + across * dir[0];
        }
        sim.set_positions(&now)?;
        sim.step(gpu, FRAME_DT)?;
    }
    sim.set_inv_mass(inv_mass)?;
    for _ in 0..30 {
        sim.step(gpu, FRAME_DT)?;
    }
    Ok(())
}

/// The scene of `seed`: a garment folded, lifted and dropped (see the module docs), as an
/// animated mesh of the 24 frames of the fall, with what made it.
pub fn scene(gpu: &Gpu, seed: u64, images: Option<&ImageFolder>) -> DataResult<(AnimatedMesh, ClothRecord)> {
    let mut rng = Rng::new(seed);
    let kind = [GarmentKind::Towel, GarmentKind::Shirt, GarmentKind::Shorts][rng.below(3) as usize];
    let pat = pattern(kind, &mut rng);
    let yaw = rng.range(0.0, std::f64::consts::TAU) as f32;
    let params = params();
    let mesh = garment_mesh(&pat, yaw)?;
    let inv_mass = mesh.inv_mass.clone();
    let mut sim = ClothSim::new(gpu, &mesh, params)?;
    let folds = 1 + rng.below(2) as usize;
    for _ in 0..folds {
        let a = rng.range(0.0, std::f64::consts::TAU) as f32;
        let origin = [rng.range(-0.1, 0.1) as f32, rng.range(-0.1, 0.1) as f32];
        fold(gpu, &mut sim, &inv_mass, origin, [a.cos(), a.sin()])?;
    }
    // Lift and drop from rest.
    let drop_height = rng.range(0.2, 0.6) as f32;
    let mut lifted = sim.positions()?;
    for y in lifted.iter_mut().skip(1).step_by(3) {
        *y += drop_height;
    }
    let mut dropped = mesh.clone();
    dropped.positions = lifted.chunks(3).map(|p| [p[0], p[1], p[2]]).collect();
    let mut sim = ClothSim::new(gpu, &dropped, params)?;
    let mut frames = Vec::with_capacity(FRAMES);
    let mut centre_of_mass = Vec::with_capacity(FRAMES);
    for f in 0..FRAMES {
        if f > 0 {
            sim.step(gpu, FRAME_DT)?;
        }
        let x = sim.positions()?;
        let verts: Vec<[f32; 3]> = x.chunks(3).map(|p| to_scene([p[0], p[1], p[2]])).collect();
        let n = verts.len() as f64;
        let com = [0, 1, 2].map(|k| (verts.iter().map(|v| v[k] as f64).sum::<f64>() / n) as f32);
        centre_of_mass.push(com);
        frames.push(verts);
    }
    let texture = match images {
        Some(folder) => folder.random_crop(&mut rng)?,
        None => procedural(&mut rng),
    };
    let tris = pat.triangles.len();
    let record = ClothRecord {
        kind,
        particles: pat.points.len(),
        folds,
        drop_height,
        gravity: GRAVITY,
        ground: GROUND,
        up: up(),
        frame_seconds: FRAME_DT,
        centre_of_mass,
    };
    let mesh = AnimatedMesh {
        frames,
        triangles: pat.triangles,
        uvs: pat.uvs,
        tri_texture: vec![0; tris],
        textures: vec![texture],
        colours: Vec::new(),
    };
    Ok((mesh, record))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_are_one_connected_layer_of_their_kind() {
        for (seed, kind) in [(1, GarmentKind::Towel), (2, GarmentKind::Shirt), (3, GarmentKind::Shorts)] {
            let p = pattern(kind, &mut Rng::new(seed));
            assert!(p.points.len() > 100, "{kind:?}: {} particles", p.points.len());
            assert_eq!(p.uvs.len(), p.points.len());
            assert!(p.uvs.iter().flatten().all(|v| (0.0..=1.0).contains(v)));
            // Every particle is a corner of some triangle.
            let mut used = vec![false; p.points.len()];
            p.triangles.iter().flatten().for_each(|&v| used[v as usize] = true);
            assert!(used.iter().all(|&u| u), "{kind:?}: a particle without a triangle");
            // One piece: a flood fill over the triangles reaches every particle.
            let mut parent: Vec<usize> = (0..p.points.len()).collect();
            fn root(parent: &mut [usize], mut i: usize) -> usize {
                while parent[i] != i {
                    parent[i] = parent[parent[i]];
                    i = parent[i];
                }
                i
            }
            for t in &p.triangles {
                for k in 1..3 {
                    let (a, b) = (root(&mut parent, t[0] as usize), root(&mut parent, t[k] as usize));
                    parent[a] = b;
                }
            }
            let r0 = root(&mut parent, 0);
            assert!((0..p.points.len()).all(|i| root(&mut parent, i) == r0), "{kind:?}: more than one piece");
        }
        // Shorts have a gap between the legs: the bottom centre is not cloth.
        let p = pattern(GarmentKind::Shorts, &mut Rng::new(3));
        let bottom = p.points.iter().map(|q| q[1]).fold(f32::INFINITY, f32::min);
        assert!(!p.points.iter().any(|q| q[0].abs() < 0.02 && q[1] < bottom + 0.1));
    }
}
