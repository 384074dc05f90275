//! Procedural animated objects, seeded and reproducible.
//!
//! A scene holds one to three objects, each one of: a walker (torso, head and four swinging
//! legs, walking along its heading), an arm (a chain of two to four links on a turning base),
//! a pendulum (one or two swinging links with a bob, under a bar), a deforming shape (a box,
//! cylinder or sphere that bends, twists or pulses) and a rigid body (tumbling and drifting).
//! Objects get a random size, heading and place; some lose or gain a part, or appear or
//! disappear as a whole, during the clip. Each part is a primitive whose UVs come from its
//! own parametrisation on the rest pose (fixed on frame 0), textured with a procedural
//! pattern or a crop of a user image. The clip is normalised into [-1, 1]^3 as a whole.
//!
//! The same seed gives the same mesh, bit for bit: every random draw comes from one
//! [`Rng`] in a fixed order, and the maths is plain f32 on the CPU.

use std::f32::consts::{PI, TAU};

use velox_engine::rng::Rng;

use crate::math::{add, rotate, scale, V3};
use crate::mesh::{AnimatedMesh, Texture};
use crate::texture::{procedural, ImageFolder};
use crate::DataResult;

/// Frames in a clip (docs/models.md: tau = frame / 100, 24 frames; `velox_io::frames`).
pub use velox_io::frames::FRAMES;

/// A primitive in its rest pose.
#[derive(Clone, Default)]
struct Prim {
    pos: Vec<V3>,
    uv: Vec<[f32; 2]>,
    tris: Vec<[u32; 3]>,
}

impl Prim {
    /// A grid of (cols + 1) x (rows + 1) vertices over (u, v) in [0, 1]^2, mapped by `at`.
    fn grid(cols: usize, rows: usize, at: impl Fn(f32, f32) -> V3) -> Prim {
        let mut p = Prim::default();
        for j in 0..=rows {
            for i in 0..=cols {
                let (u, v) = (i as f32 / cols as f32, j as f32 / rows as f32);
                p.pos.push(at(u, v));
                p.uv.push([u, v]);
            }
        }
        let w = cols as u32 + 1;
        for j in 0..rows as u32 {
            for i in 0..cols as u32 {
                let a = j * w + i;
                p.tris.push([a, a + 1, a + w + 1]);
                p.tris.push([a, a + w + 1, a + w]);
            }
        }
        p
    }

    fn extend(&mut self, other: Prim) {
        let base = self.pos.len() as u32;
        self.pos.extend(other.pos);
        self.uv.extend(other.uv);
        self.tris.extend(other.tris.iter().map(|t| t.map(|i| i + base)));
    }

    /// UV sphere of radius `r` at the origin; u around y, v from pole to pole.
    fn sphere(r: f32) -> Prim {
        Prim::grid(24, 12, |u, v| {
            let (th, ph) = (u * TAU, v * PI);
            [r * ph.sin() * th.cos(), -r * ph.cos(), r * ph.sin() * th.sin()]
        })
    }

    /// Closed cylinder of radius `r` along +y from 0 to `h`, `rings` segments along its length.
    fn cylinder(r: f32, h: f32, rings: usize) -> Prim {
        let mut p = Prim::grid(16, rings, |u, v| {
            let th = u * TAU;
            [r * th.cos(), v * h, r * th.sin()]
        });
        for (y, flip) in [(0.0, true), (h, false)] {
            // A cap: a disc grid collapsed at its centre.
            let mut cap = Prim::grid(16, 1, |u, v| {
                let th = u * TAU;
                [v * r * th.cos(), y, v * r * th.sin()]
            });
            for uv in &mut cap.uv {
                *uv = [0.5 + 0.5 * uv[1] * (uv[0] * TAU).cos(), 0.5 + 0.5 * uv[1] * (uv[0] * TAU).sin()];
            }
            if flip {
                cap.tris.iter_mut().for_each(|t| t.swap(1, 2));
            }
            p.extend(cap);
        }
        p
    }

    /// Box of half-sizes `h` centred at the origin; each face an n x n grid with its own UVs.
    fn cuboid(h: V3, n: usize) -> Prim {
        let mut p = Prim::default();
        for axis in 0..3 {
            for sign in [-1.0f32, 1.0] {
                let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
                p.extend(Prim::grid(n, n, |u, v| {
                    let mut q = [0.0; 3];
                    q[axis] = sign * h[axis];
                    q[a] = (2.0 * u - 1.0) * h[a];
                    q[b] = (2.0 * v - 1.0) * h[b] * sign;
                    q
                }));
            }
        }
        p
    }
}

/// Builds one object's animated mesh part by part.
struct Builder {
    mesh: AnimatedMesh,
    parts: Vec<std::ops::Range<usize>>,
}

impl Builder {
    fn new(textures: Vec<Texture>) -> Builder {
        let mesh = AnimatedMesh { frames: vec![Vec::new(); FRAMES], textures, ..Default::default() };
        Builder { mesh, parts: Vec::new() }
    }

    /// Adds `prim` with texture `tex`; `pose(frame, t, rest)` places a rest vertex at a frame,
    /// `t = frame / (FRAMES - 1)` in [0, 1].
    fn part(&mut self, prim: Prim, tex: u32, pose: impl Fn(f32, V3) -> V3) -> usize {
        let base = self.mesh.uvs.len();
        for (f, verts) in self.mesh.frames.iter_mut().enumerate() {
            let t = f as f32 / (FRAMES - 1) as f32;
            verts.extend(prim.pos.iter().map(|&p| pose(t, p)));
        }
        self.mesh.triangles.extend(prim.tris.iter().map(|t| t.map(|i| i + base as u32)));
        self.mesh.tri_texture.extend(std::iter::repeat_n(tex, prim.tris.len()));
        self.mesh.uvs.extend(prim.uv);
        self.parts.push(base..self.mesh.uvs.len());
        self.parts.len() - 1
    }

    /// Collapses part `i` to its centroid in the frames where `present(frame)` is false.
    fn hide_part(&mut self, i: usize, present: impl Fn(usize) -> bool) {
        let range = self.parts[i].clone();
        for (f, verts) in self.mesh.frames.iter_mut().enumerate() {
            if present(f) {
                continue;
            }
            let n = range.len() as f32;
            let c = verts[range.clone()].iter().fold([0.0; 3], |a, &v| add(a, v));
            let c = scale(c, 1.0 / n);
            verts[range.clone()].iter_mut().for_each(|v| *v = c);
        }
    }
}

/// Draws `n` textures for an object: a crop of the user's images half of the time when a
/// folder is given, else a procedural pattern.
fn textures(rng: &mut Rng, n: usize, images: Option<&ImageFolder>) -> DataResult<Vec<Texture>> {
    (0..n)
        .map(|_| match images {
            Some(folder) if rng.uniform() < 0.5 => folder.random_crop(rng),
            _ => Ok(procedural(rng)),
        })
        .collect()
}

const Y: V3 = [0.0, 1.0, 0.0];
const Z: V3 = [0.0, 0.0, 1.0];

fn walker(rng: &mut Rng, tex: Vec<Texture>) -> Builder {
    let mut b = Builder::new(tex);
    let cycles = rng.range(1.0, 2.0) as f32;
    let swing = rng.range(0.3, 0.7) as f32;
    let speed = rng.range(0.3, 1.0) as f32;
    let leg = rng.range(0.45, 0.7) as f32;
    let half = [rng.range(0.3, 0.5) as f32, rng.range(0.1, 0.18) as f32, rng.range(0.15, 0.25) as f32];
    let body = move |t: f32, p: V3| {
        let bob = 0.04 * (2.0 * TAU * cycles * t).sin();
        add(p, [speed * (t - 0.5), leg + bob, 0.0])
    };
    b.part(Prim::cuboid(half, 4), 0, body);
    let r = 0.6 * half[1].max(0.1);
    b.part(Prim::sphere(r), 1, move |t, p| body(t, add(p, [half[0] + 0.7 * r, half[1] + 0.5 * r, 0.0])));
    for k in 0..4 {
        let hip = [
            if k < 2 { 0.75 } else { -0.75 } * half[0],
            -half[1],
            if k % 2 == 0 { 0.7 } else { -0.7 } * half[2],
        ];
        let phase = if k == 0 || k == 3 { 0.0 } else { PI };
        let mut cyl = Prim::cylinder(0.05, leg, 6);
        cyl.pos.iter_mut().for_each(|p| p[1] = -p[1]);
        cyl.tris.iter_mut().for_each(|t| t.swap(1, 2));
        b.part(cyl, 2 + (k as u32 % 2), move |t, p| {
            let a = swing * (TAU * cycles * t + phase).sin();
            body(t, add(hip, rotate(p, Z, a)))
        });
    }
    b
}

fn arm(rng: &mut Rng, tex: Vec<Texture>) -> Builder {
    let mut b = Builder::new(tex);
    let links = 2 + rng.below(3) as usize;
    let lengths: Vec<f32> = (0..links).map(|_| rng.range(0.35, 0.6) as f32).collect();
    let amps: Vec<f32> = (0..links).map(|_| rng.range(0.3, 1.0) as f32).collect();
    let phases: Vec<f32> = (0..links).map(|_| rng.range(0.0, TAU as f64) as f32).collect();
    let cycles = rng.range(0.5, 1.5) as f32;
    let turn = rng.range(-1.5, 1.5) as f32;
    let yaw = move |t: f32, p: V3| rotate(p, Y, turn * t);
    let link_lengths = lengths.clone();
    b.part(Prim::cylinder(0.25, 0.1, 1), 0, yaw);
    // Forward kinematics: link i starts where link i - 1 ends, at the summed joint angles.
    let pose = move |t: f32, i: usize, p: V3| {
        let mut start = [0.0, 0.1, 0.0];
        let mut angle = 0.0;
        for k in 0..=i {
            angle += amps[k] * (TAU * cycles * t + phases[k]).sin();
            if k < i {
                start = add(start, rotate([0.0, lengths[k], 0.0], Z, angle));
            }
        }
        yaw(t, add(start, rotate(p, Z, angle)))
    };
    let pose = std::rc::Rc::new(pose);
    for (i, &length) in link_lengths.iter().enumerate() {
        let radius = 0.08 - 0.01 * i as f32;
        let pose = pose.clone();
        b.part(Prim::cylinder(radius, length, 4), 1 + (i as u32 % 2), move |t, p| pose(t, i, p));
    }
    b
}

fn pendulum(rng: &mut Rng, tex: Vec<Texture>) -> Builder {
    let mut b = Builder::new(tex);
    let double = rng.uniform() < 0.5;
    let l1 = rng.range(0.6, 1.0) as f32;
    let l2 = rng.range(0.4, 0.7) as f32;
    let a1 = rng.range(0.4, 1.0) as f32;
    let a2 = rng.range(0.3, 1.2) as f32;
    let cycles = rng.range(0.7, 1.5) as f32;
    let phase = rng.range(0.0, TAU as f64) as f32;
    let top = [0.0, l1 + if double { l2 } else { 0.0 } + 0.2, 0.0];
    b.part(Prim::cuboid([0.5, 0.05, 0.08], 3), 0, move |_, p| add(p, top));
    let th1 = move |t: f32| a1 * (TAU * cycles * t).cos();
    let th2 = move |t: f32| th1(t) + a2 * (TAU * 1.7 * cycles * t + phase).cos();
    let hang = |p: V3| [p[0], -p[1], p[2]];
    b.part(Prim::cylinder(0.025, l1, 4), 1, move |t, p| add(top, rotate(hang(p), Z, th1(t))));
    let end1 = move |t: f32| add(top, rotate([0.0, -l1, 0.0], Z, th1(t)));
    if double {
        b.part(Prim::sphere(0.08), 2, move |t, p| add(end1(t), p));
        b.part(Prim::cylinder(0.02, l2, 4), 1, move |t, p| add(end1(t), rotate(hang(p), Z, th2(t))));
        b.part(Prim::sphere(0.15), 2, move |t, p| add(end1(t), add(rotate([0.0, -l2, 0.0], Z, th2(t)), p)));
    } else {
        b.part(Prim::sphere(0.2), 2, move |t, p| add(end1(t), p));
    }
    b
}

fn deformer(rng: &mut Rng, tex: Vec<Texture>) -> Builder {
    let mut b = Builder::new(tex);
    let h = rng.range(1.0, 1.8) as f32;
    let prim = match rng.below(3) {
        0 => {
            let w = rng.range(0.15, 0.4) as f32;
            let mut p = Prim::cuboid([w, 0.5 * h, rng.range(0.15, 0.4) as f32], 8);
            p.pos.iter_mut().for_each(|q| q[1] += 0.5 * h);
            p
        }
        1 => Prim::cylinder(rng.range(0.15, 0.35) as f32, h, 16),
        _ => {
            let mut p = Prim::sphere(0.5 * h);
            p.pos.iter_mut().for_each(|q| q[1] += 0.5 * h);
            p
        }
    };
    let kind = rng.below(3);
    let amount = rng.range(0.5, 1.0) as f32;
    let cycles = rng.range(0.5, 1.5) as f32;
    let wave = rng.range(1.0, 4.0) as f32;
    b.part(prim, 0, move |t, p| {
        let s = (TAU * cycles * t).sin();
        match kind {
            // Bend in the xy plane: the axis becomes an arc of curvature k, lengths kept.
            0 => {
                let k = amount * 1.5 * s / h;
                if k.abs() < 1e-4 {
                    return p;
                }
                let r = 1.0 / k;
                let th = p[1] * k;
                [r - (r - p[0]) * th.cos(), (r - p[0]) * th.sin(), p[2]]
            }
            // Twist about y, the angle growing with height.
            1 => rotate(p, Y, amount * 2.0 * s * p[1] / h),
            // Pulse: radial scale, a wave travelling up the shape.
            _ => {
                let g = 1.0 + 0.35 * amount * (TAU * cycles * t - wave * p[1]).sin();
                [p[0] * g, p[1], p[2] * g]
            }
        }
    });
    b
}

fn rigid(rng: &mut Rng, tex: Vec<Texture>) -> Builder {
    let mut b = Builder::new(tex);
    let prim = match rng.below(3) {
        0 => Prim::cuboid(
            [rng.range(0.2, 0.5) as f32, rng.range(0.2, 0.5) as f32, rng.range(0.2, 0.5) as f32],
            3,
        ),
        1 => {
            let mut p = Prim::cylinder(rng.range(0.15, 0.35) as f32, 0.8, 3);
            p.pos.iter_mut().for_each(|q| q[1] -= 0.4);
            p
        }
        _ => Prim::sphere(rng.range(0.25, 0.45) as f32),
    };
    let axis = crate::camera::random_direction(rng);
    let spin = rng.range(1.0, 4.0) as f32;
    let drift = scale(crate::camera::random_direction(rng), rng.range(0.2, 0.8) as f32);
    b.part(prim, 0, move |t, p| add(rotate(p, axis, spin * t), scale(drift, t - 0.5)));
    b
}

/// Object kinds, in the order [`object`] draws them.
pub const KINDS: [&str; 5] = ["walker", "arm", "pendulum", "deformer", "rigid"];

/// One procedural object: its kind and animated mesh (in its own frame, not normalised).
pub fn object(rng: &mut Rng, images: Option<&ImageFolder>) -> DataResult<(&'static str, AnimatedMesh)> {
    let kind = rng.below(KINDS.len() as u32) as usize;
    let tex = textures(rng, 4, images)?;
    let mut b = match kind {
        0 => walker(rng, tex),
        1 => arm(rng, tex),
        2 => pendulum(rng, tex),
        3 => deformer(rng, tex),
        _ => rigid(rng, tex),
    };
    // A part (never the first, which holds the others up) may appear or disappear mid-clip.
    if b.parts.len() > 1 && rng.uniform() < 0.35 {
        let part = 1 + rng.below(b.parts.len() as u32 - 1) as usize;
        let cut = 4 + rng.below(FRAMES as u32 - 8) as usize;
        let appears = rng.uniform() < 0.5;
        b.hide_part(part, move |f| (f >= cut) == appears);
    }
    Ok((KINDS[kind], b.mesh))
}

/// What a procedural scene is made of, for its metadata.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SceneRecipe {
    pub seed: u64,
    pub objects: Vec<String>,
}

/// A scene of one to three objects placed side by side with random headings and sizes, the
/// later ones sometimes appearing or disappearing as a whole; normalised into [-1, 1]^3.
pub fn scene(seed: u64, images: Option<&ImageFolder>) -> DataResult<(SceneRecipe, AnimatedMesh)> {
    let mut rng = Rng::new(seed);
    let count = 1 + rng.below(3) as usize;
    let mut mesh = AnimatedMesh::default();
    let mut names = Vec::new();
    for i in 0..count {
        let (name, mut obj) = object(&mut rng, images)?;
        let yaw = rng.range(0.0, TAU as f64) as f32;
        let size = rng.range(0.7, 1.3) as f32;
        let offset = if i == 0 {
            [0.0; 3]
        } else {
            let a = rng.range(0.0, TAU as f64) as f32;
            [1.1 * a.cos(), rng.range(-0.3, 0.3) as f32, 1.1 * a.sin()]
        };
        for v in obj.frames.iter_mut().flatten() {
            *v = add(scale(rotate(*v, Y, yaw), size), offset);
        }
        if i > 0 && rng.uniform() < 0.3 {
            let cut = 4 + rng.below(FRAMES as u32 - 8) as usize;
            let appears = rng.uniform() < 0.5;
            let whole = std::iter::once(0..obj.num_vertices()).collect();
            let mut b = Builder { mesh: obj, parts: whole };
            b.hide_part(0, move |f| (f >= cut) == appears);
            obj = b.mesh;
        }
        names.push(name.to_string());
        mesh.append(obj);
    }
    mesh.normalise();
    mesh.validate()?;
    Ok((SceneRecipe { seed, objects: names }, mesh))
}
