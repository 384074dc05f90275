//! The cloth solver (XPBD, `velox_engine::ops::cloth`) on lavapipe: free fall as gravity says,
//! the device against the f64 reference, a pinned cloth coming to rest with its edges near
//! their lengths, a thousand random drops with no NaN and nothing below the ground, two
//! layers that do not pass through each other, the same bits every run, and bad meshes
//! refused by name.

use crate::common;
use common::*;
use velox::engine::ops::cloth::{reference, ClothMesh, ClothParams, ClothSim, Constraint};

/// A square `side x side` grid of spacing `h` in the plane y = `y`, centred on (`cx`, `cz`).
fn grid(side: usize, h: f32, y: f32, cx: f32, cz: f32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let c = (side - 1) as f32 * h / 2.0;
    let pos = (0..side * side)
        .map(|i| [cx + (i % side) as f32 * h - c, y, cz + (i / side) as f32 * h - c])
        .collect();
    let mut tris = Vec::new();
    for r in 0..side - 1 {
        for q in 0..side - 1 {
            let a = (r * side + q) as u32;
            let s = side as u32;
            tris.push([a, a + 1, a + s]);
            tris.push([a + 1, a + s + 1, a + s]);
        }
    }
    (pos, tris)
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
}

/// A whole cloth scene: the garment falls as gravity says until it lands, ends on the ground,
/// stays in the scene's box, and the same seed gives the same bits.
#[test]
fn a_cloth_scene_falls_lands_and_repeats() {
    use velox::data::cloth::{scene, up, FRAME_DT, GRAVITY, GROUND};
    let gpu = gpu();
    let (mesh, record) = scene(&gpu, 11, None).unwrap();
    assert_eq!(mesh.frames.len(), 24);
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
