//! The cloth solver (XPBD, `velox_engine::ops::cloth`) on lavapipe: free fall as gravity says,
//! the device against the f64 reference, a pinned cloth coming to rest with its edges near
//! their lengths, a thousand random drops with no NaN and nothing below the ground, two
//! layers that do not pass through each other, the same bits every run, and bad meshes
//! refused by name. Then each constraint family with its own parameter, by construction (the
//! constraints the device holds, the push constants its kernels read, the garments' mesh and
//! parameters) and by effect against closed forms: stretch (Hooke's law), bending (a hinge's
//! droop), friction and restitution at a contact, damping in flight, and self-collision's
//! radius and exclusion, each changing what it controls and leaving the others' results.

use crate::common;
use common::*;
use velox::engine::ops::cloth::{reference, ClothMesh, ClothParams, ClothSim, Constraint};

/// A square `side x side` grid of spacing `h` in the plane y = `y`, centred on (`cx`, `cz`).
fn grid(side: usize, h: f32, y: f32, cx: f32, cz: f32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let c = (side - 1) as f32 * h / 2.0;
    let pos = (0..side * side)
        .map(|i| [cx + (i % side) as f32 * h - c, y, cz + (i / side) as f32 * h - c])
        .collect();
    (pos, ClothMesh::grid_triangles(side))
}

fn sheet(side: usize, h: f32, y: f32) -> ClothMesh {
    let (p, t) = grid(side, h, y, 0.0, 0.0);
    ClothMesh::from_triangles(p, &t, 0.0, 1e-4).unwrap()
}

#[test]
fn a_cloth_in_free_fall_falls_as_gravity_says() {
    let gpu = gpu();
    let params = ClothParams { damping: 0.0, substeps: 10, ..ClothParams::default() };
    let mesh = sheet(6, 0.05, 0.5);
    let mut sim = ClothSim::new(&gpu, &mesh, params).unwrap();
    let (dt, frames) = (0.01f32, 20);
    for _ in 0..frames {
        sim.step(&gpu, dt).unwrap();
    }
    let x = sim.positions().unwrap();
    let t = dt as f64 * frames as f64;
    let h = dt as f64 / 10.0;
    let k = (frames * 10) as f64;
    // Symplectic Euler: y_k = y0 - g h^2 k (k + 1) / 2, within g t h / 2 + g h^2 of the
    // continuous y0 - g t^2 / 2. The velocities are re-derived from f32 positions each
    // substep, which early in the fall (moves of 1e-5 against a spacing of 6e-8 between f32
    // values near 0.5) costs about 1e-4 over these 200 substeps (measured 1.0e-4).
    let discrete = 0.5 - 9.81 * h * h * k * (k + 1.0) / 2.0;
    let continuous = 0.5 - 9.81 * t * t / 2.0;
    for (i, p) in x.chunks(3).enumerate() {
        assert!((p[1] as f64 - discrete).abs() < 2e-4, "particle {i}: y {} against {discrete}", p[1]);
        assert!((p[1] as f64 - continuous).abs() <= 9.81 * t * h / 2.0 + 9.81 * h * h + 1e-5);
        let m = mesh.positions[i];
        assert!((p[0] - m[0]).abs() < 1e-6 && (p[2] - m[2]).abs() < 1e-6, "particle {i} drifted sideways");
    }
}

/// A crumpled cloth hung by one corner just over the ground, with bending, self-collision,
/// friction and bounce: the device's substeps against the f64 reference's. The reference run
/// counts what happened (ground contacts, bounces, particles pushed apart by self-collision),
/// and runs again without friction, without bounce and without self-collision to show each
/// changed the result: a device that skipped one would then differ from the reference.
#[test]
fn the_device_matches_the_f64_reference() {
    let gpu = gpu();
    let mut rng = Rng::new(3);
    let (mut pos, tris) = grid(7, 0.03, -0.972, 0.0, 0.0);
    for p in pos.iter_mut() {
        for v in p.iter_mut() {
            *v += rng.range(-0.008, 0.008) as f32;
        }
    }
    let mut mesh = ClothMesh::from_triangles(pos, &tris, 1e-6, 1e-3).unwrap();
    mesh.inv_mass[0] = 0.0;
    // Particles 0.04 apart collide: diagonal neighbours (0.042 at rest) come within reach.
    let params =
        ClothParams { substeps: 4, restitution: 0.3, radius: 0.02, exclude: 0.035, ..ClothParams::default() };
    let frames = 8;
    let floor = params.ground as f64 + params.radius as f64;
    // The reference, counting ground contacts, bounces and self-collision pushes.
    let run = |q: &ClothParams| {
        let mut state = reference::State::new(&mesh);
        let (mut contacts, mut bounces, mut close) = (0, 0, 0);
        for _ in 0..frames * q.substeps {
            reference::substep(&mut state, &mesh, q, 0.01 / q.substeps as f64);
            for (x, v) in state.x.iter().zip(&state.v) {
                if x[1] == floor {
                    contacts += 1;
                    bounces += (v[1] > 0.0) as usize;
                }
            }
            close += pairs_within(&state.x, &mesh.rest_positions, 2.0 * q.radius as f64, q.exclude as f64);
        }
        (state, contacts, bounces, close)
    };
    let (state, contacts, bounces, close) = run(&params);
    let mut sim = ClothSim::new(&gpu, &mesh, params).unwrap();
    for _ in 0..frames {
        sim.step(&gpu, 0.01).unwrap();
    }
    let want: Vec<f64> = state.x.iter().flatten().copied().collect();
    let got = sim.positions().unwrap();
    assert_nmse("positions after 8 frames", &got, &want, 1e-10);
    let want_v: Vec<f64> = state.v.iter().flatten().copied().collect();
    // A velocity is a position difference over a substep of 2.5 ms: near y = -0.98 f32 values
    // lie 6e-8 apart (2.4e-5 in velocity), and friction divides by slides of some 1e-5. On
    // lavapipe: positions 3.3e-12, velocities 7.8e-6 (at most 3.7e-4 off, of up to 0.3).
    assert_nmse("velocities after 8 frames", &sim.velocities().unwrap(), &want_v, 3e-5);
    // What the comparison covered: contacts with the ground, bounces, and pairs within reach
    // of each other (summed over the substeps).
    if verbose() {
        eprintln!("ground contacts {contacts}, bounces {bounces}, pairs within reach {close}");
    }
    assert!(
        contacts >= 100 && bounces >= 10 && close >= 10,
        "contacts {contacts}, bounces {bounces}, close pairs {close}"
    );
    // Each of friction, bounce and self-collision changes the result well beyond the device's
    // distance from the reference.
    for (what, q) in [
        ("friction", ClothParams { friction: 0.0, ..params }),
        ("bounce", ClothParams { restitution: 0.0, ..params }),
        ("self-collision", ClothParams { collide: false, ..params }),
    ] {
        let without: Vec<f64> = run(&q).0.x.iter().flatten().copied().collect();
        let e = nmse(&got, &without);
        if verbose() {
            eprintln!("without {what}: nmse {e:.2e} from the device's");
        }
        assert!(e > 1e-8, "without {what} the result is the same ({e:.2e})");
    }
}

/// Pairs of particles closer than `reach` that self-collision does not exclude.
fn pairs_within(x: &[[f64; 3]], rest: &[[f32; 3]], reach: f64, exclude: f64) -> usize {
    let d = |a: [f64; 3], b: [f64; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let mut n = 0;
    for i in 0..x.len() {
        for j in i + 1..x.len() {
            let r = d(rest[i].map(|v| v as f64), rest[j].map(|v| v as f64));
            n += (r >= exclude && d(x[i], x[j]) < reach) as usize;
        }
    }
    n
}

#[test]
fn a_pinned_cloth_comes_to_rest_with_its_edges_near_their_lengths() {
    let gpu = gpu();
    let side = 10;
    let mut mesh = sheet(side, 0.04, 0.5);
    mesh.inv_mass[0] = 0.0;
    mesh.inv_mass[side - 1] = 0.0;
    // Measured: damping 2 leaves it swinging at 0.19 after 3 s (0.01 after 6); 5 brings it to
    // 0.007 by 3 s, and a floor of about 0.004 from the rigid edges' corrections.
    let params = ClothParams { damping: 5.0, ..ClothParams::default() };
    let mut sim = ClothSim::new(&gpu, &mesh, params).unwrap();
    for _ in 0..300 {
        sim.step(&gpu, 0.01).unwrap();
    }
    let v = sim.velocities().unwrap();
    let fastest = v.chunks(3).map(|u| (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt()).fold(0.0, f32::max);
    assert!(fastest < 0.02, "still moving at {fastest} after 3 s");
    let x = sim.positions().unwrap();
    let at = |i: u32| [x[3 * i as usize], x[3 * i as usize + 1], x[3 * i as usize + 2]];
    let stretch = mesh
        .constraints
        .iter()
        .filter(|c| c.compliance == 0.0)
        .map(|c: &Constraint| {
            let (a, b) = (at(c.a), at(c.b));
            let len = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
            (len - c.rest).abs() / c.rest
        })
        .fold(0.0, f32::max);
    assert!(stretch < 0.05, "an edge is {stretch} off its length");
    // The pins held, and the cloth hangs below them.
    assert_eq!(at(0), mesh.positions[0]);
    assert!(x.chunks(3).all(|p| p[1] <= 0.5 + 1e-4));
}

#[test]
fn a_thousand_random_drops_end_on_the_ground_with_no_nan() {
    let gpu = gpu();
    let mut rng = Rng::new(7);
    let mut mesh = ClothMesh::default();
    for d in 0..1000 {
        let (cx, cz) = ((d % 32) as f32 * 0.5, (d / 32) as f32 * 0.5);
        let (mut pos, tris) = grid(4, 0.04, rng.range(-0.95, 1.0) as f32, cx, cz);
        // A random tilt and a random stiffness.
        let tilt = rng.range(-1.0, 1.0) as f32;
        for p in pos.iter_mut() {
            p[1] += tilt * (p[0] - cx);
        }
        let m =
            ClothMesh::from_triangles(pos, &tris, rng.range(0.0, 1e-5) as f32, rng.range(0.0, 1e-2) as f32)
                .unwrap();
        let base = mesh.positions.len() as u32;
        mesh.constraints.extend(m.constraints.iter().map(|c| Constraint {
            a: c.a + base,
            b: c.b + base,
            ..*c
        }));
        mesh.positions.extend(m.positions);
        mesh.rest_positions.extend(m.rest_positions);
        mesh.inv_mass.extend(m.inv_mass);
    }
    let params = ClothParams { substeps: 8, restitution: 0.2, ..ClothParams::default() };
    let mut sim = ClothSim::new(&gpu, &mesh, params).unwrap();
    for _ in 0..100 {
        sim.step(&gpu, 0.01).unwrap();
    }
    let x = sim.positions().unwrap();
    assert!(x.iter().chain(&sim.velocities().unwrap()).all(|v| v.is_finite()), "a NaN or Inf");
    let lowest = x.chunks(3).map(|p| p[1]).fold(f32::INFINITY, f32::min);
    assert!(lowest >= params.ground + params.radius - 1e-4, "a particle at y {lowest}, below the ground");
    // After a second every drop has landed (the highest started 2 above the ground).
    let highest = x.chunks(3).map(|p| p[1]).fold(f32::NEG_INFINITY, f32::max);
    assert!(highest < params.ground + 0.3, "a particle still at y {highest}");
}

/// Two sheets, one above the other, fall onto the ground: the upper one ends on the lower one,
/// not through it.
#[test]
fn layers_do_not_pass_through_each_other() {
    let gpu = gpu();
    let (lower, tris) = grid(8, 0.03, -0.9, 0.0, 0.0);
    let (upper, _) = grid(8, 0.03, -0.8, 0.0, 0.0);
    let n = lower.len() as u32;
    let mut all_tris = tris.clone();
    all_tris.extend(tris.iter().map(|t| t.map(|v| v + n)));
    let mut pos = lower;
    pos.extend(upper);
    let mut mesh = ClothMesh::from_triangles(pos, &all_tris, 0.0, 1e-3).unwrap();
    // The two sheets are far apart in the rest shape, so they collide.
    for p in mesh.rest_positions[n as usize..].iter_mut() {
        p[0] += 10.0;
    }
    let params = ClothParams { radius: 0.01, exclude: 0.035, ..ClothParams::default() };
    let mut sim = ClothSim::new(&gpu, &mesh, params).unwrap();
    for _ in 0..60 {
        sim.step(&gpu, 0.01).unwrap();
    }
    let x = sim.positions().unwrap();
    let ys: Vec<f32> = x.chunks(3).map(|p| p[1]).collect();
    let top_of_lower = ys[..n as usize].iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let bottom_of_upper = ys[n as usize..].iter().copied().fold(f32::INFINITY, f32::min);
    assert!(
        bottom_of_upper > top_of_lower + params.radius,
        "the upper sheet reaches down to {bottom_of_upper}, the lower one up to {top_of_lower}"
    );
    // Without self-collision it falls through.
    let mut sim = ClothSim::new(&gpu, &mesh, ClothParams { collide: false, ..params }).unwrap();
    for _ in 0..60 {
        sim.step(&gpu, 0.01).unwrap();
    }
    let x = sim.positions().unwrap();
    let gap: f32 = x[3 * n as usize + 1] - x[1];
    assert!(gap.abs() < params.radius, "without collision the sheets should meet, gap {gap}");
}

#[test]
fn the_same_drop_gives_the_same_bits() {
    let gpu = gpu();
    let mut rng = Rng::new(5);
    let (mut pos, tris) = grid(12, 0.02, -0.7, 0.0, 0.0);
    for p in pos.iter_mut() {
        p[1] += 0.2 * (p[0] * 9.0).sin() * rng.range(0.5, 1.0) as f32;
    }
    let mesh = ClothMesh::from_triangles(pos, &tris, 1e-6, 1e-3).unwrap();
    let run = || {
        let mut sim = ClothSim::new(&gpu, &mesh, ClothParams::default()).unwrap();
        for _ in 0..30 {
            sim.step(&gpu, 0.01).unwrap();
        }
        sim.positions().unwrap().iter().map(|v| v.to_bits()).collect::<Vec<u32>>()
    };
    assert_eq!(run(), run());
}

#[test]
fn bad_meshes_and_parameters_are_refused_by_name() {
    let gpu = gpu();
    let (pos, tris) = grid(3, 0.1, 0.0, 0.0, 0.0);
    let err = |m: &ClothMesh, p: ClothParams| ClothSim::new(&gpu, m, p).err().expect("refused").to_string();
    let mut m = ClothMesh::from_triangles(pos.clone(), &tris, 0.0, 0.0).unwrap();
    m.positions[4][1] = f32::NAN;
    assert!(err(&m, ClothParams::default()).contains("position 4"));
    let mut m = ClothMesh::from_triangles(pos.clone(), &tris, 0.0, 0.0).unwrap();
    m.inv_mass[2] = -1.0;
    assert!(err(&m, ClothParams::default()).contains("particle 2"));
    let mut m = ClothMesh::from_triangles(pos.clone(), &tris, 0.0, 0.0).unwrap();
    m.constraints[0].b = 99;
    assert!(err(&m, ClothParams::default()).contains("constraint 0"));
    assert!(ClothMesh::from_triangles(pos.clone(), &[[0, 1, 42]], 0.0, 0.0)
        .unwrap_err()
        .to_string()
        .contains("42"));
    let m = ClothMesh::from_triangles(pos, &tris, 0.0, 0.0).unwrap();
    assert!(err(&m, ClothParams { restitution: 2.0, ..ClothParams::default() }).contains("parameters"));
    let mut sim = ClothSim::new(&gpu, &m, ClothParams::default()).unwrap();
    assert!(sim.step(&gpu, f32::NAN).unwrap_err().to_string().contains("seconds"));
    assert!(sim.set_velocities(&[0.0; 26]).unwrap_err().to_string().contains("velocities"));
    assert!(sim.set_velocities(&[f32::INFINITY; 27]).unwrap_err().to_string().contains("velocities"));
    // The first bad value is named with its particle.
    let mut x = sim.positions().unwrap();
    x[7] = f32::NAN;
    assert!(sim.set_positions(&x).unwrap_err().to_string().contains("positions of particle 2 holds NaN"));
    let mut w = vec![1.0; 9];
    w[4] = -1.0;
    assert!(sim.set_inv_mass(&w).unwrap_err().to_string().contains("inverse masses of particle 4 holds -1"));
}

/// A whole cloth scene: the garment falls as gravity says until it lands, ends on the ground,
/// stays in the scene's box, and the same seed gives the same bits.
#[test]
fn a_cloth_scene_falls_lands_and_repeats() {
    use velox::data::cloth::{scene, up, FRAME_DT, GRAVITY, GROUND};
    let gpu = gpu();
    let (mesh, record) = scene(&gpu, 11, None).unwrap();
    assert_eq!(mesh.frames.len(), 24);
    assert_eq!(
        (record.gravity, record.ground, record.frame_seconds, record.up),
        (GRAVITY, GROUND, FRAME_DT, up())
    );
    assert!(mesh.frames.iter().flatten().flatten().all(|v| v.is_finite() && v.abs() <= 1.0));
    let u = up();
    let height = |p: [f32; 3]| (0..3).map(|k| p[k] as f64 * u[k] as f64).sum::<f64>();
    let com: Vec<f64> = record.centre_of_mass.iter().map(|&c| height(c)).collect();
    assert!(com.windows(2).all(|w| w[1] <= w[0] + 1e-4), "the centre of mass rose: {com:?}");
    // Free fall until the lowest particle nears the ground (the air's damping of 1 per second
    // slows it by a few per cent).
    let lowest = |f: usize| mesh.frames[f].iter().map(|&p| height(p)).fold(f64::INFINITY, f64::min);
    let free = (1..24).take_while(|&f| lowest(f) > GROUND as f64 + 0.05).last().unwrap_or(0);
    assert!(free >= 3, "the cloth landed by frame {free}");
    let t = free as f64 * FRAME_DT as f64;
    let fallen = com[0] - com[free];
    let expected = GRAVITY as f64 * t * t / 2.0;
    assert!((fallen - expected).abs() < 0.1 * expected, "fell {fallen} in {t} s, gravity says {expected}");
    assert!(lowest(23) >= GROUND as f64 - 1e-3, "a particle below the ground");
    let (again, _) = scene(&gpu, 11, None).unwrap();
    assert_eq!(mesh, again);
    let (other, _) = scene(&gpu, 12, None).unwrap();
    assert_ne!(mesh.frames[0].len(), 0);
    assert!(other.frames != mesh.frames);
}

// Each constraint family with its own parameter: by construction (what the device holds and
// what its kernels read) and by effect (that parameter alone moves what physics says it moves,
// and the others leave it where they cannot reach it). The values are all different, so a
// family handed another's parameter is seen.

/// Pairs of particles, each (low, high).
type Pairs = Vec<(u32, u32)>;

/// The edges of `tris` and the opposite corners of the two triangles of every interior edge,
/// worked out here apart from the library.
fn families(tris: &[[u32; 3]]) -> (Pairs, Pairs) {
    let mut sides: std::collections::BTreeMap<(u32, u32), Vec<u32>> = Default::default();
    for t in tris {
        for (a, b, c) in [(t[0], t[1], t[2]), (t[1], t[2], t[0]), (t[2], t[0], t[1])] {
            sides.entry((a.min(b), a.max(b))).or_default().push(c);
        }
    }
    let bends = sides.values().filter(|o| o.len() == 2).map(|o| (o[0].min(o[1]), o[0].max(o[1]))).collect();
    (sides.into_keys().collect(), bends)
}

fn distance(p: [f32; 3], q: [f32; 3]) -> f32 {
    ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
}

/// Fails, naming the first difference, unless `got` holds the constraints of `want` (each
/// pair either way round, with the same rest length and compliance), in any order.
fn assert_same_constraints(what: &str, got: &[Constraint], want: &[Constraint]) {
    let keyed = |c: &[Constraint]| {
        let mut k: Vec<_> = c.iter().map(|c| ((c.a.min(c.b), c.a.max(c.b)), c.rest, c.compliance)).collect();
        k.sort_by(|x, y| x.0.cmp(&y.0).then(x.1.total_cmp(&y.1)).then(x.2.total_cmp(&y.2)));
        k
    };
    let (got, want) = (keyed(got), keyed(want));
    assert_eq!(got.len(), want.len(), "{what}: {} constraints, want {}", got.len(), want.len());
    if let Some((g, w)) = got.iter().zip(&want).find(|(g, w)| g != w) {
        panic!("{what}: constraint (pair, rest, compliance) {g:?}, want {w:?}");
    }
}

/// Every edge's constraint carries the stretch compliance and the edge's length, every
/// interior edge's bending constraint (between the opposite corners) the bending compliance
/// and the corners' distance, one of each and no more; and the device holds exactly these
/// (read back from its buffers). Would catch: the bending constraints built with the stretch
/// compliance or the stretch ones with the bending (the two arguments swapped), a bending
/// constraint given its edge's length as its rest, the device's compliance buffer filled with
/// the rest lengths, or constraints lost in the colouring.
#[test]
fn each_constraint_family_carries_its_own_compliance_and_rest_length() {
    let gpu = gpu();
    let (mut pos, tris) = grid(5, 0.04, 0.0, 0.0, 0.0);
    // An uneven sheet, so that no two rest lengths agree by accident.
    let mut rng = Rng::new(4);
    for p in pos.iter_mut() {
        p[0] += rng.range(-0.005, 0.005) as f32;
        p[2] += rng.range(-0.005, 0.005) as f32;
    }
    let (stretch, bend) = (3e-6f32, 7e-3f32);
    let mesh = ClothMesh::from_triangles(pos.clone(), &tris, stretch, bend).unwrap();
    let (edges, bends) = families(&tris);
    let want: Vec<Constraint> = edges
        .iter()
        .map(|&(a, b)| (a, b, stretch))
        .chain(bends.iter().map(|&(a, b)| (a, b, bend)))
        .map(|(a, b, compliance)| Constraint {
            a,
            b,
            rest: distance(pos[a as usize], pos[b as usize]),
            compliance,
        })
        .collect();
    assert_eq!((edges.len(), bends.len()), (56, 40), "a 5 x 5 grid's edges and interior edges");
    assert_same_constraints("the mesh", &mesh.constraints, &want);
    let sim = ClothSim::new(&gpu, &mesh, ClothParams::default()).unwrap();
    assert_same_constraints("the device", &sim.constraints().unwrap(), &want);
    // A mesh without constraints holds none (its one bound slot is padding).
    let lone = ClothMesh {
        positions: vec![[0.0; 3]],
        inv_mass: vec![1.0],
        rest_positions: vec![[0.0; 3]],
        ..Default::default()
    };
    assert!(ClothSim::new(&gpu, &lone, ClothParams::default()).unwrap().constraints().unwrap().is_empty());
}

/// The push constants every kernel reads hold each parameter in its own field, the collision
/// cells two radii across. Would catch: friction and restitution, radius and exclusion,
/// gravity and ground swapped on the way to the shaders, damping given the friction, cells of
/// one radius (then pairs between one and two radii apart are missed).
#[test]
fn the_kernels_read_each_parameter_from_its_own_field() {
    let gpu = gpu();
    let (pos, tris) = grid(3, 0.05, 0.0, 0.0, 0.0);
    let mesh = ClothMesh::from_triangles(pos, &tris, 0.0, 1e-3).unwrap();
    let q = ClothParams {
        gravity: 7.5,
        ground: -0.25,
        friction: 0.35,
        restitution: 0.65,
        radius: 0.015,
        exclude: 0.045,
        substeps: 7,
        collide: true,
        damping: 0.9,
    };
    let sim = ClothSim::new(&gpu, &mesh, q).unwrap();
    let p = sim.substep_params(0.002);
    assert_eq!((p.n, p.dt), (9, 0.002));
    assert_eq!((p.gravity, p.ground), (q.gravity, q.ground));
    assert_eq!((p.friction, p.restitution), (q.friction, q.restitution));
    assert_eq!((p.radius, p.exclude, p.cell), (q.radius, q.exclude, 2.0 * q.radius));
    assert_eq!(p.damping, q.damping);
}

/// Runs `frames` frames of 0.01 s and returns the positions and velocities.
fn settle(mesh: &ClothMesh, q: ClothParams, frames: usize) -> (Vec<f32>, Vec<f32>) {
    let gpu = gpu();
    let mut sim = ClothSim::new(&gpu, mesh, q).unwrap();
    for _ in 0..frames {
        sim.step(&gpu, 0.01).unwrap();
    }
    (sim.positions().unwrap(), sim.velocities().unwrap())
}

/// Where `f` changes sign in `lo .. hi` (one root), by bisection.
fn root(f: impl Fn(f64) -> f64, mut lo: f64, mut hi: f64) -> f64 {
    assert!(f(lo) * f(hi) < 0.0, "no root between {lo} and {hi}");
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if f(lo) * f(mid) <= 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Air only: no ground within reach, no self-collision; gravity 9.81, 10 substeps of 1 ms.
fn in_the_air(damping: f32) -> ClothParams {
    ClothParams { ground: -100.0, collide: false, substeps: 10, damping, ..ClothParams::default() }
}

/// A particle hung from two pinned ones by two edges of one triangle (no interior edge, so no
/// bending constraint) stretches them as Hooke's law says with stiffness 1 / compliance: at
/// rest, each edge's extension over the compliance is its tension, and the two tensions hold
/// the particle's weight (solved here by bisection, with the XPBD substep's own `h^2 / w` added
/// to the compliance; measured 5.42e-3 against 5.43e-3, and 1.075e-2 against 1.075e-2 at
/// twice the compliance). Twice the compliance, about twice the stretch; the bending
/// compliance, which this mesh has no constraint of, changes no bit. Would catch: the stretch constraints
/// built with the bending compliance, the device reading another buffer as compliance, the
/// compliance not divided by h^2 (a rigid edge).
#[test]
fn stretch_compliance_alone_sets_how_far_a_hung_cloth_stretches() {
    let (half, depth) = (0.05f64, 0.1f64);
    let pos = vec![[-half as f32, 0.0, 0.0], [half as f32, 0.0, 0.0], [0.0, -depth as f32, 0.0]];
    let hang = |stretch: f32, bend: f32| {
        let mut mesh = ClothMesh::from_triangles(pos.clone(), &[[0, 1, 2]], stretch, bend).unwrap();
        mesh.inv_mass[0] = 0.0;
        mesh.inv_mass[1] = 0.0;
        let (x, v) = settle(&mesh, in_the_air(50.0), 60);
        assert!(v.iter().all(|v| v.abs() < 1e-4), "still moving: {v:?}");
        assert!(x[6].abs() < 1e-4 && x[8].abs() < 1e-6, "the particle swung sideways: {x:?}");
        x[7] as f64
    };
    let rest = (half * half + depth * depth).sqrt();
    let h = 1e-3;
    let expected = |alpha: f64| {
        // Tension (l - rest) / alpha along each edge; their vertical parts carry g.
        let alpha = alpha + h * h;
        -root(
            |y| 2.0 * ((half * half + y * y).sqrt() - rest) / alpha * y / (half * half + y * y).sqrt() - 9.81,
            depth,
            2.0 * depth,
        )
    };
    let mut stretched = Vec::new();
    for alpha in [1e-3f32, 2e-3] {
        let y = hang(alpha, 1e-5);
        let want = expected(alpha as f64);
        let (got_e, want_e) =
            ((half * half + y * y).sqrt() - rest, (half * half + want * want).sqrt() - rest);
        if verbose() {
            eprintln!("stretch compliance {alpha}: extension {got_e:.5}, Hooke's law {want_e:.5}");
        }
        assert!(
            (got_e - want_e).abs() < 0.01 * want_e,
            "compliance {alpha}: extension {got_e}, want {want_e}"
        );
        stretched.push(got_e);
        // The bending compliance has nothing to act on here.
        assert_eq!(
            hang(alpha, 1.0).to_bits(),
            y.to_bits(),
            "the bending compliance moved a mesh without bending"
        );
    }
    assert!(stretched[1] > 1.8 * stretched[0], "twice the compliance stretched {stretched:?}");
}

/// A hinge: two triangles on a pinned edge along z, one wing pinned flat, the other free to
/// swing down about the edge. Its rigid edges keep it on a circle about the hinge, so only the
/// bending constraint (between the wings' tips, compressed as the wing droops) holds it up:
/// at rest the bending force `2 a (1 - cos(phi / 2)) / compliance` times its lever `a sin(phi /
/// 2)` balances the weight's `g a cos(phi)` (solved here; measured 0.5188 rad against 0.5192,
/// and 0.7754 against 0.7757 with a bend four times softer). A softer bend droops further,
/// here by 49 %; the stretch compliance (0 or 1e-7) moves the angle by 2.5e-4 of itself at
/// most.
/// Would catch: the bending constraints built with the stretch compliance (the hinge stays
/// flat), or with the rest length of the hinge edge instead of the tips' distance (it folds).
#[test]
fn bend_compliance_alone_sets_how_far_a_hinge_droops() {
    let (a, b) = (0.05f32, 0.03f32);
    let pos = vec![[-a, 0.0, 0.0], [0.0, 0.0, -b], [0.0, 0.0, b], [a, 0.0, 0.0]];
    let droop = |stretch: f32, bend: f32| {
        let mut mesh =
            ClothMesh::from_triangles(pos.clone(), &[[0, 1, 2], [1, 3, 2]], stretch, bend).unwrap();
        for i in 0..3 {
            mesh.inv_mass[i] = 0.0;
        }
        let (x, v) = settle(&mesh, in_the_air(20.0), 150);
        assert!(v.iter().all(|v| v.abs() < 1e-3), "still moving: {v:?}");
        (-x[10] as f64).atan2(x[9] as f64)
    };
    let h = 1e-3;
    let expected = |alpha: f64| {
        let (a, alpha) = (a as f64, alpha + h * h);
        root(
            |phi| 2.0 * a * (1.0 - (phi / 2.0).cos()) * (phi / 2.0).sin() - alpha * 9.81 * phi.cos(),
            1e-6,
            1.5,
        )
    };
    let mut angles = Vec::new();
    for alpha in [1e-4f32, 4e-4] {
        let phi = droop(0.0, alpha);
        let want = expected(alpha as f64);
        if verbose() {
            eprintln!("bend compliance {alpha}: droop {phi:.4} rad, equilibrium {want:.4}");
        }
        assert!((phi - want).abs() < 0.01 * want, "bend compliance {alpha}: droop {phi} rad, want {want}");
        let loose = droop(1e-7, alpha);
        if verbose() {
            eprintln!(
                "  with stretch compliance 1e-7: {loose:.5} rad ({:.1e} of it)",
                (loose - phi).abs() / phi
            );
        }
        assert!(
            (loose - phi).abs() < 3e-3 * phi,
            "the stretch compliance moved the bend: {loose} against {phi}"
        );
        angles.push(phi);
    }
    assert!(angles[1] > 1.4 * angles[0], "a softer bend drooped {angles:?}");
}

/// Particles by themselves (no constraints), at `positions` with `velocities`, far apart in the
/// rest shape.
fn loose_particles(gpu: &Gpu, positions: &[[f32; 3]], velocities: &[[f32; 3]], q: ClothParams) -> ClothSim {
    let mesh = ClothMesh {
        positions: positions.to_vec(),
        inv_mass: vec![1.0; positions.len()],
        constraints: Vec::new(),
        rest_positions: (0..positions.len()).map(|i| [10.0 * i as f32, 0.0, 0.0]).collect(),
    };
    let sim = ClothSim::new(gpu, &mesh, q).unwrap();
    sim.set_velocities(&velocities.iter().flatten().copied().collect::<Vec<f32>>()).unwrap();
    sim
}

/// Particles thrown down and sideways onto the ground, one substep of 10 ms: each lands on
/// `ground + radius`, its sideways speed cut to `1 - friction depth / slide` of itself, its
/// upward speed `restitution` times its downward one (worked out here from the rule). More
/// friction, slower sideways; more restitution, a higher bounce; and each leaves the other's
/// result bit for bit. Would catch: friction and restitution swapped (in the host's push
/// constants or the shader), the bounce taken from the friction, the floor at the ground
/// without the radius, the depth measured from the ground.
#[test]
fn friction_and_restitution_each_act_alone_at_a_contact() {
    let gpu = gpu();
    let (h, g, ground, radius) = (0.01f64, 7.0f64, 0.1f32, 0.01f32);
    let start = [[0.0, 0.13, 0.0], [1.0, 0.13, 0.0], [2.0, 0.125, 1.0]];
    let thrown = [[1.0, -2.0, 0.0], [2.0, -3.0, 0.0], [0.0, -2.5, 1.5]];
    let contact = |friction: f32, restitution: f32| {
        let q = ClothParams {
            gravity: g as f32,
            ground,
            friction,
            restitution,
            radius,
            substeps: 1,
            collide: false,
            damping: 0.0,
            ..ClothParams::default()
        };
        let mut sim = loose_particles(&gpu, &start, &thrown, q);
        sim.step(&gpu, h as f32).unwrap();
        let (x, v) = (sim.positions().unwrap(), sim.velocities().unwrap());
        for (i, (s, t)) in start.iter().zip(&thrown).enumerate() {
            let falling = t[1] as f64 - h * g;
            let y = s[1] as f64 + h * falling;
            let floor = ground as f64 + radius as f64;
            assert!(y < floor, "particle {i} does not reach the ground");
            let slide = h * (t[0] as f64).hypot(t[2] as f64);
            let keep = (1.0 - friction as f64 * (floor - y) / slide).max(0.0);
            let want = [keep * t[0] as f64, restitution as f64 * -falling, keep * t[2] as f64];
            for k in 0..3 {
                let got = v[3 * i + k] as f64;
                assert!(
                    (got - want[k]).abs() < 1e-4 * (1.0 + want[k].abs()),
                    "particle {i} velocity {k}: {got}, want {}",
                    want[k]
                );
            }
            assert_eq!(x[3 * i + 1], ground + radius, "particle {i} is not on the ground");
        }
        v
    };
    let base = contact(0.3, 0.5);
    let rough = contact(0.6, 0.5);
    let bouncy = contact(0.3, 0.8);
    let (sideways, up) = (|v: &[f32]| [v[0], v[3], v[8]], |v: &[f32]| [v[1], v[4], v[7]]);
    for k in 0..3 {
        assert!(sideways(&rough)[k] < sideways(&base)[k] && up(&bouncy)[k] > up(&base)[k]);
    }
    assert_eq!(up(&rough), up(&base), "friction changed the bounce");
    assert_eq!(sideways(&bouncy), sideways(&base), "restitution changed the slide");
}

/// A particle thrown through the air: each substep its velocity gains `h g` downward and is
/// then scaled by `1 - damping h` (worked out here over the 80 substeps). More damping, a
/// slower particle; friction, restitution and the collision radius (nothing to touch) change
/// no bit. Would catch: the damping given the friction or the restitution, damping applied
/// twice or not at all, or a contact rule reaching a particle in the air.
#[test]
fn damping_alone_slows_a_flight() {
    let gpu = gpu();
    // Velocities are re-derived from f32 positions each substep: near the origin and in
    // substeps of 2.5 ms that costs some 1e-5 over the flight (near 0.5, 6.6e-4).
    let fly = |q: ClothParams| {
        let mut sim = loose_particles(&gpu, &[[0.0; 3]], &[[0.2, 1.0, -0.1]], q);
        for _ in 0..20 {
            sim.step(&gpu, 0.01).unwrap();
        }
        sim.velocities().unwrap()
    };
    let mut speeds = Vec::new();
    for damping in [0.0f32, 2.0] {
        let q = ClothParams { damping, substeps: 4, ..in_the_air(0.0) };
        let v = fly(q);
        let (h, keep) = (2.5e-3f64, 1.0 - damping as f64 * 2.5e-3);
        let mut want = [0.2f64, 1.0, -0.1];
        for _ in 0..80 {
            want[1] -= h * 9.81;
            want = want.map(|w| w * keep);
        }
        for k in 0..3 {
            assert!(
                (v[k] as f64 - want[k]).abs() < 2e-4,
                "damping {damping}: velocity {k} {} against {}",
                v[k],
                want[k]
            );
        }
        speeds.push(v[0]);
        for other in [
            ClothParams { friction: 0.9, restitution: 0.9, ..q },
            ClothParams { radius: 0.3, collide: true, ..q },
        ] {
            assert_eq!(fly(other), v, "a contact parameter changed a flight, damping {damping}");
        }
    }
    assert!(speeds[1] < speeds[0], "damping did not slow it: {speeds:?}");
}

/// Self-collision, one parameter at a time. A particle dropped onto a pinned one comes to rest
/// two radii above it (less the `h^2 g` one substep of gravity presses in), for either radius,
/// and the exclusion distance (below their rest distance) changes no bit. Two particles
/// falling side by side 0.03 apart, within reach (two radii, 0.04): closer than the exclusion
/// in the rest shape they stay 0.03 apart, whatever the radius; with the exclusion below 0.03
/// they are pushed out to 0.04. Would catch: the radius and the exclusion swapped, cells of one
/// radius (a particle above the next cell goes unseen and sinks in), the exclusion measured in
/// the current shape instead of the rest shape.
#[test]
fn self_collision_radius_and_exclusion_each_act_alone() {
    let air = ClothParams { collide: true, damping: 20.0, ..in_the_air(0.0) };
    let stack = |radius: f32, exclude: f32| {
        let q = ClothParams { radius, exclude, ..air };
        let mesh = ClothMesh {
            positions: vec![[0.0, 0.003, 0.0], [0.0, 0.2, 0.0]],
            inv_mass: vec![0.0, 1.0],
            constraints: Vec::new(),
            rest_positions: vec![[0.0; 3], [1.0, 0.0, 0.0]],
        };
        settle(&mesh, q, 100).0
    };
    for radius in [0.02f32, 0.03] {
        let x = stack(radius, 0.05);
        let gap = x[4] - x[1];
        let want = 2.0 * radius - 1e-6 * 9.81;
        assert!((gap - want).abs() < 1e-5, "radius {radius}: resting {gap} above, want {want}");
        assert_eq!((x[3], x[5]), (0.0, 0.0));
        assert_eq!(stack(radius, 0.5), x, "the exclusion changed a collision of particles far apart at rest");
    }
    // One substep: a push becomes a velocity, which would carry them on apart.
    let side_by_side = |radius: f32, exclude: f32| {
        let q = ClothParams { radius, exclude, substeps: 1, ..air };
        let pos = vec![[-0.015, 0.5, 0.0], [0.015, 0.5, 0.0]];
        let mesh = ClothMesh {
            positions: pos.clone(),
            inv_mass: vec![1.0, 1.0],
            constraints: Vec::new(),
            rest_positions: pos,
        };
        let x = settle(&mesh, q, 1).0;
        x[3] - x[0]
    };
    assert_eq!(side_by_side(0.02, 0.035), 0.03, "rest neighbours collided");
    assert_eq!(side_by_side(0.03, 0.035), 0.03, "the radius reached rest neighbours");
    let apart = side_by_side(0.02, 0.025);
    assert!((apart - 0.04).abs() < 1e-6, "not rest neighbours, they end {apart} apart, not two radii");
}

/// The garments' mesh and motion as the scenes build them: every edge carries
/// `STRETCH_COMPLIANCE`, every interior edge's opposite corners `BEND_COMPLIANCE`, the rest
/// shape is the flat pattern (so every edge and diagonal is inside `EXCLUDE` and reach is less
/// than the spacing), and the solver gets each named constant in its own field. Would catch:
/// the scene's two compliances swapped, friction and restitution or radius and exclusion
/// swapped in the scene's parameters, the rest shape left at the yawed mesh's own.
#[test]
fn a_garment_carries_the_scenes_own_compliances_and_parameters() {
    use velox::data::cloth::{
        garment_mesh, params, pattern, GarmentKind, BEND_COMPLIANCE, DAMPING, EXCLUDE, FRICTION, GRAVITY,
        GROUND, RADIUS, RESTITUTION, SPACING, STRETCH_COMPLIANCE,
    };
    assert_ne!(STRETCH_COMPLIANCE, BEND_COMPLIANCE);
    let pat = pattern(GarmentKind::Shirt, &mut Rng::new(8));
    let mesh = garment_mesh(&pat, 0.7).unwrap();
    let (edges, bends) = families(&pat.triangles);
    let flat: Vec<[f32; 3]> = pat.points.iter().map(|p| [p[0], 0.0, p[1]]).collect();
    assert_eq!(mesh.rest_positions, flat);
    assert!(mesh.positions.iter().all(|p| p[1] == GROUND + RADIUS));
    let want: Vec<Constraint> = edges
        .iter()
        .map(|&(a, b)| (a, b, STRETCH_COMPLIANCE))
        .chain(bends.iter().map(|&(a, b)| (a, b, BEND_COMPLIANCE)))
        .map(|(a, b, compliance)| Constraint {
            a,
            b,
            rest: distance(mesh.positions[a as usize], mesh.positions[b as usize]),
            compliance,
        })
        .collect();
    assert_same_constraints("the garment", &mesh.constraints, &want);
    for c in mesh.constraints.iter().filter(|c| c.compliance == STRETCH_COMPLIANCE) {
        let at_rest = distance(flat[c.a as usize], flat[c.b as usize]);
        assert!(at_rest < EXCLUDE && at_rest > 2.0 * RADIUS, "an edge of {at_rest} at rest");
    }
    assert!(2.0 * RADIUS < SPACING && EXCLUDE > SPACING * 2f32.sqrt());
    let q = params();
    assert_eq!((q.gravity, q.ground), (GRAVITY, GROUND));
    assert_eq!((q.friction, q.restitution, q.damping), (FRICTION, RESTITUTION, DAMPING));
    assert_eq!((q.radius, q.exclude), (RADIUS, EXCLUDE));
}
