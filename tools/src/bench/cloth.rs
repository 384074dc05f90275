//! `velox bench cloth`: frames of cloth simulation per second (`velox_engine::ops::cloth`) for
//! a typical garment of `velox data cloth` (a t-shirt pattern at the data's spacing, about
//! 350 particles) and for a towel-sized sheet of 48 x 48 particles (24 x 24 on CPU devices or
//! with `--quick`), falling tilted onto the ground at the data's 20 substeps a frame of 0.01 s,
//! with and without self-collision. Each frame is one recording, timed by GPU timestamps; the
//! error is the positions of the last timed frame against an untimed run's (the solver is
//! deterministic, so 0).

use velox_engine::ops::cloth::{ClothMesh, ClothParams, ClothSim};
use velox_engine::rng::Rng;
use velox_engine::stats::{max_abs_err, nmse};
use velox_engine::{Gpu, Result};

use super::{print_header, print_row, time_gpu, Record, SizeSet};

fn sheet(side: usize) -> Result<ClothMesh> {
    let h = 0.025f32;
    let c = (side - 1) as f32 * h / 2.0;
    // A little tilt, so the fall is not a flat landing.
    let pos = (0..side * side)
        .map(|i| {
            let (x, z) = ((i % side) as f32 * h - c, (i / side) as f32 * h - c);
            [x, 0.2 + 0.3 * x, z]
        })
        .collect();
    ClothMesh::from_triangles(pos, &ClothMesh::grid_triangles(side), 1e-7, 1e-3)
}

/// The t-shirt of the cloth data's seed 2, flat and tilted like the sheet.
fn garment() -> Result<ClothMesh> {
    let pattern = velox_data::cloth::pattern(velox_data::cloth::GarmentKind::Shirt, &mut Rng::new(2));
    let pos = pattern.points.iter().map(|p| [p[0], 0.2 + 0.3 * p[0], p[1]]).collect();
    ClothMesh::from_triangles(pos, &pattern.triangles, 1e-7, 1e-3)
}

pub fn run(gpu: &Gpu, sizes: SizeSet, repeats: u32) -> Result<Vec<Record>> {
    let side = if sizes.small() { 24 } else { 48 };
    let device = gpu.caps().name.clone();
    println!("device: {device}; a t-shirt of the cloth data and a {side} x {side} sheet, frames of 0.01 s");
    print_header();
    let mut out = Vec::new();
    for (what, mesh) in [("t-shirt", garment()?), ("sheet", sheet(side)?)] {
        out.extend(bench_mesh(gpu, &device, repeats, what, &mesh)?);
    }
    Ok(out)
}

fn bench_mesh(gpu: &Gpu, device: &str, repeats: u32, what: &str, mesh: &ClothMesh) -> Result<Vec<Record>> {
    let mut out = Vec::new();
    for collide in [false, true] {
        let params = ClothParams { collide, ..ClothParams::default() };
        let frames_before = 30;
        let run = |frames: usize| -> Result<(ClothSim, Vec<f32>)> {
            let mut sim = ClothSim::new(gpu, mesh, params)?;
            for _ in 0..frames {
                sim.step(gpu, 0.01)?;
            }
            let x = sim.positions()?;
            Ok((sim, x))
        };
        // Mid-fall, then timed frames; the reference replays the same frames untimed.
        let (sim, _) = run(frames_before)?;
        let h = 0.01 / params.substeps as f32;
        let t = time_gpu(gpu, repeats, |rec| {
            for _ in 0..params.substeps {
                sim.record_substep(rec, h)?;
            }
            Ok(())
        })?;
        let got = sim.positions()?;
        let (_, want) = run(frames_before + repeats as usize + 1)?;
        let want: Vec<f64> = want.iter().map(|&v| v as f64).collect();
        let name = if collide { format!("cloth {what}, self-collision") } else { format!("cloth {what}") };
        let shape =
            format!("{} particles, {} colours, {} substeps", sim.particles(), sim.colours(), params.substeps);
        let r = Record::timed(name, shape, "f32", device, t, repeats, 1e3 / t.0, "frame/s").error(
            nmse(&got, &want),
            max_abs_err(&got, &want),
            "an untimed run of the same frames",
        );
        print_row(&r);
        out.push(r);
    }
    Ok(out)
}
