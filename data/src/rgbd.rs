//! RGBD videos, the tracking task's input (docs/models.md, 3D tracking network): colour frames
//! (`fFF.png`) and depth frames (`fFF_depth.exr`, one f32 channel `Z` of camera-space z, 0
//! where no surface) from one pinhole camera, and the 4D colour cloud their back-projection
//! gives, which the frozen encoder turns into the tracker's tokens.
//!
//! A scene's video is `SCENE/video/` with the camera `video` of `SCENE/cameras.json`; any
//! other video is a folder of the same frames with the camera in `camera.json` (the fields of
//! [`Camera`]: width, height, fx, fy, cx, cy, rotation rows and translation, world to camera,
//! the world being the scene's [-1, 1]^3 box).

use std::path::Path;

use velox_engine::rng::Rng;

use crate::camera::Camera;
use crate::format::{check_camera, read_json, CameraSet};
use crate::pipeline::{fill_in_frame_order, Reservoir, FPS};
use crate::procedural::FRAMES;
use crate::{DataError, DataResult};

/// Most points the back-projection keeps by default (a 128 px video shows about 5 000 surface
/// pixels a frame, 120 000 over the clip).
pub const DEFAULT_POINTS: usize = 100_000;
/// How far a back-projected point may lie outside [-1, 1]^3 before the video is refused
/// (depth rounding of a surface on the box's face) and clamped onto it.
const BOX_SLACK: f32 = 1e-2;

/// A video's frames and its camera.
#[derive(Clone, Debug)]
pub struct RgbdVideo {
    pub camera: Camera,
    /// Per frame, row-major RGB `[h, w, 3]` in [0, 1].
    pub rgb: Vec<Vec<f32>>,
    /// Per frame, row-major camera-space depth `[h, w]`, 0 where no surface.
    pub depth: Vec<Vec<f32>>,
}

fn invalid(path: &Path, why: impl std::fmt::Display) -> DataError {
    DataError::Invalid(format!("{}: {why}", path.display()))
}

/// Colour frame `f` (`fFF.png`) of the video in `dir` seen by `camera`: row-major RGB
/// `[h, w, 3]` in [0, 1], its size checked against the camera.
pub fn read_colour_frame(dir: &Path, camera: &Camera, f: usize) -> DataResult<Vec<f32>> {
    let png = dir.join(format!("f{f:02}.png"));
    let (colour, cw, ch) = velox_io::image::read_png(&png)
        .map_err(|e| DataError::Io(format!("colour frame {f} of the video: {e}")))?;
    let (w, h) = (camera.width, camera.height);
    if (cw, ch) != (w, h) {
        return Err(invalid(&png, format!("{cw} x {ch} pixels, the camera's image is {w} x {h}")));
    }
    Ok(colour)
}

/// The colour of each point in `rgb` (a colour frame of `camera`, as [`read_colour_frame`]
/// gives): the pixel it projects into, or the image's pixel nearest to where it projects.
pub fn colours_at(rgb: &[f32], camera: &Camera, points: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let pixel = |x: f32, n: usize| if x.is_finite() { (x.max(0.0) as usize).min(n - 1) } else { 0 };
    points
        .iter()
        .map(|&p| {
            let (u, v, _) = camera.project(p);
            let i = 3 * (pixel(v, h) * w + pixel(u, w));
            [rgb[i], rgb[i + 1], rgb[i + 2]]
        })
        .collect()
}

/// Reads the [`FRAMES`] frames of the video in `dir` seen by `camera`, checking each image's
/// size against the camera and each depth for finite, non-negative values.
pub fn read_rgbd_video(dir: &Path, camera: Camera) -> DataResult<RgbdVideo> {
    let (w, h) = (camera.width, camera.height);
    let (mut rgb, mut depth) = (Vec::new(), Vec::new());
    for f in 0..FRAMES {
        let exr = dir.join(format!("f{f:02}_depth.exr"));
        let colour = read_colour_frame(dir, &camera, f)?;
        let (z, dw, dh) = velox_io::image::read_exr_depth(&exr)
            .map_err(|e| DataError::Io(format!("depth frame {f} of the video: {e}")))?;
        if (dw, dh) != (w, h) {
            return Err(invalid(&exr, format!("{dw} x {dh} pixels, the camera's image is {w} x {h}")));
        }
        if let Some(i) = z.iter().position(|d| !(d.is_finite() && *d >= 0.0)) {
            return Err(invalid(
                &exr,
                format!(
                    "pixel ({}, {}) has depth {}: depths are finite, 0 where no surface",
                    i as u32 % w,
                    i as u32 / w,
                    z[i]
                ),
            ));
        }
        rgb.push(colour);
        depth.push(z);
    }
    Ok(RgbdVideo { camera, rgb, depth })
}

/// The video of the scene in `scene` (`video/` and the `video` camera of `cameras.json`).
pub fn read_scene_video(scene: &Path) -> DataResult<RgbdVideo> {
    read_rgbd_video(&scene.join("video"), scene_video_camera(scene)?)
}

/// The `video` camera of a scene's `cameras.json`, checked.
pub fn scene_video_camera(scene: &Path) -> DataResult<Camera> {
    let path = scene.join("cameras.json");
    let cams: CameraSet = read_json(&path)?;
    let camera = cams.video.ok_or_else(|| invalid(&path, "the scene has no video camera"))?;
    check_camera("the video camera", &camera).map_err(|why| invalid(&path, why))?;
    Ok(camera)
}

/// A camera file (`camera.json` of a video folder), checked.
pub fn read_camera(path: &Path) -> DataResult<Camera> {
    let camera: Camera = read_json(path)?;
    check_camera("the camera", &camera).map_err(|why| invalid(path, why))?;
    Ok(camera)
}

/// Reads a video folder of any origin: `camera.json` and the frames (see the module docs).
pub fn read_video_folder(dir: &Path) -> DataResult<RgbdVideo> {
    read_rgbd_video(dir, read_camera(&dir.join("camera.json"))?)
}

/// The 4D colour cloud (x, y, z, r, g, b, tau) of the video: every pixel with a depth,
/// back-projected at its centre, with its colour and its frame's time; a uniform draw of
/// `max_points` of them (seeded) when there are more, in frame order. Fails when no pixel
/// has a depth, or one back-projects outside the scene's box.
pub fn rgbd_cloud(video: &RgbdVideo, max_points: usize, seed: u64) -> DataResult<Vec<[f32; 7]>> {
    let cam = &video.camera;
    let mut rng = Rng::new(seed);
    let mut reservoir = Reservoir { k: max_points.max(1), seen: 0, items: Vec::new() };
    for (f, (rgb, depth)) in video.rgb.iter().zip(&video.depth).enumerate() {
        for (i, &z) in depth.iter().enumerate().filter(|(_, z)| **z > 0.0) {
            let (u, v) = ((i as u32 % cam.width) as f32 + 0.5, (i as u32 / cam.width) as f32 + 0.5);
            let p = cam.unproject(u, v, z);
            if p.iter().any(|x| x.abs() > 1.0 + BOX_SLACK) {
                return Err(DataError::Invalid(format!(
                    "pixel ({}, {}) of frame {f} back-projects to {p:?}, outside the scene's [-1, 1]^3 box: \
                     the camera or the depth is not in the scene's units",
                    u - 0.5,
                    v - 0.5
                )));
            }
            let c = &rgb[3 * i..3 * i + 3];
            let x = p.map(|x| x.clamp(-1.0, 1.0));
            reservoir.offer(&mut rng, [x[0], x[1], x[2], c[0], c[1], c[2], f as f32 / FPS]);
        }
    }
    if reservoir.items.is_empty() {
        return Err(DataError::Invalid("no pixel of the video has a depth: nothing to back-project".into()));
    }
    let n = reservoir.items.len();
    Ok(fill_in_frame_order(reservoir.items, n, &mut rng))
}
