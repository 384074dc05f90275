//! Pinhole cameras and the data's camera rigs (docs/models.md, Data conventions).
//!
//! Convention: world to camera `x_c = R x_w + t`, camera x right, y down, z forward (depth is
//! the camera-space z); pixel `u = fx x_c / z + cx`, `v = fy y_c / z + cy`, pixel (i, j) covers
//! [i, i + 1) x [j, j + 1) and its centre is (i + 0.5, j + 0.5). The world is y-up, as in glTF.

use velox_engine::rng::Rng;

use crate::math::{add, cross, dot, length, normalize, scale, sub, V3};

pub use velox_engine::ops::raster::Camera;

/// A camera at `eye` looking at `target` with a square image of `res` pixels and a field of
/// view of `fov_deg` degrees, the world's y up (z when looking along y).
pub fn look_at(eye: V3, target: V3, fov_deg: f32, res: u32) -> Camera {
    let mut up = [0.0, 1.0, 0.0];
    if length(cross(normalize(sub(target, eye)), up)) < 1e-4 {
        up = [0.0, 0.0, 1.0];
    }
    Camera::look_at(eye, target, up, fov_deg, res, res)
}

/// The 16 floats the mesh rasteriser reads: rows r0 t0 r1 t1 r2 t2, then fx fy cx cy.
pub fn gpu_row(c: &Camera) -> [f32; 16] {
    let r = &c.rotation;
    let t = &c.translation;
    [
        r[0][0], r[0][1], r[0][2], t[0], r[1][0], r[1][1], r[1][2], t[1], r[2][0], r[2][1], r[2][2], t[2],
        c.fx, c.fy, c.cx, c.cy,
    ]
}

/// Radius of the input camera sphere.
pub const INPUT_RADIUS: f32 = 3.5;
/// Input cameras' field of view in degrees.
pub const INPUT_FOV: f32 = 40.0;
pub const NUM_INPUT_CAMERAS: usize = 35;
pub const NUM_SUPERVISION_CAMERAS: usize = 25;

/// The 35 input views: a Fibonacci lattice on the sphere of radius 3.5, each looking at the
/// origin, fov 40 degrees. Fixed, so every scene shares them.
pub fn input_cameras(res: u32) -> Vec<Camera> {
    let n = NUM_INPUT_CAMERAS;
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..n)
        .map(|i| {
            let y = 1.0 - (2 * i + 1) as f32 / n as f32;
            let r = (1.0 - y * y).sqrt();
            let a = golden * i as f32;
            let dir = [r * a.cos(), y, r * a.sin()];
            look_at(scale(dir, INPUT_RADIUS), [0.0; 3], INPUT_FOV, res)
        })
        .collect()
}

/// A direction uniform on the unit sphere.
pub fn random_direction(rng: &mut Rng) -> V3 {
    let y = rng.range(-1.0, 1.0) as f32;
    let a = rng.range(0.0, std::f64::consts::TAU) as f32;
    let r = (1.0 - y * y).max(0.0).sqrt();
    [r * a.cos(), y, r * a.sin()]
}

/// The 25 supervision views: distance 1.5 to 3.5 from a target drawn uniformly in the ball of
/// radius 0.25, fov 25 to 40 degrees.
pub fn supervision_cameras(rng: &mut Rng, res: u32) -> Vec<Camera> {
    (0..NUM_SUPERVISION_CAMERAS)
        .map(|_| {
            let target = loop {
                let p = [rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)].map(|v| v as f32);
                if dot(p, p) <= 1.0 {
                    break scale(p, 0.25);
                }
            };
            let dist = rng.range(1.5, 3.5) as f32;
            let fov = rng.range(25.0, 40.0) as f32;
            let eye = add(target, scale(random_direction(rng), dist));
            look_at(eye, target, fov, res)
        })
        .collect()
}

/// The conditioning video's camera: on +x at distance 1.75 to 5 looking at the origin, fov
/// 2 atan(1.25 / (r - 0.5)) so the object fills a similar share of the frame at any distance.
/// (docs/models.md rotates the world so the camera lies on +x; objects here have random
/// orientations already, so the camera is put there instead.)
pub fn video_camera(rng: &mut Rng, res: u32) -> Camera {
    video_camera_at(rng.range(1.75, 5.0) as f32, res)
}

/// The conditioning camera at distance `r` on +x, looking at the origin with the field of view
/// the data gives it there (the object fills the frame at any distance).
pub fn video_camera_at(r: f32, res: u32) -> Camera {
    let fov = 2.0 * (1.25 / (r - 0.5)).atan();
    look_at([r, 0.0, 0.0], [0.0; 3], fov.to_degrees(), res)
}

/// `count` views around the object for a generated scene: on a ring about the up axis (y), 20
/// degrees above the horizon, at distance `r`, the first a `360 / (count + 1)` degree turn
/// from +x (the conditioning camera's side), with the conditioning camera's field of view.
pub fn ring_cameras(r: f32, count: usize, res: u32) -> Vec<Camera> {
    let fov = 2.0 * (1.25 / (r - 0.5)).atan();
    let elevation = 20f32.to_radians();
    (1..=count)
        .map(|i| {
            let a = std::f32::consts::TAU * i as f32 / (count + 1) as f32;
            let dir = [elevation.cos() * a.cos(), elevation.sin(), elevation.cos() * a.sin()];
            look_at(scale(dir, r), [0.0; 3], fov.to_degrees(), res)
        })
        .collect()
}
