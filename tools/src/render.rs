//! `velox render`: renders a Gaussian PLY from a camera orbit to PNG frames and depth EXRs,
//! with a JSON record of every frame (camera, drop counts, tile pairs) beside them.

use std::path::{Path, PathBuf};

use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;
use velox_engine::ops::raster::{render_view, Camera};
use velox_engine::{Gpu, Tensor};
use velox_io::{image, ply, write_bytes};

use crate::CliResult;

#[derive(clap::Args)]
pub struct RenderArgs {
    /// Gaussians in the 3D Gaussian splatting PLY layout.
    ply: PathBuf,
    /// Folder for frame_NNNN.png, depth_NNNN.exr and render.json.
    #[arg(long, default_value = "velox-render")]
    out: PathBuf,
    /// Frames around the orbit (evenly spaced in azimuth).
    #[arg(long, default_value_t = 36, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    frames: u32,
    /// Distance from the camera to the orbit centre.
    #[arg(long, default_value_t = 4.0)]
    radius: f32,
    /// Elevation of the camera above the orbit plane, in degrees.
    #[arg(long, default_value_t = 20.0, allow_hyphen_values = true)]
    elevation: f32,
    /// Vertical field of view, in degrees.
    #[arg(long, default_value_t = 50.0)]
    fov: f32,
    #[arg(long, default_value_t = 512)]
    width: u32,
    #[arg(long, default_value_t = 512)]
    height: u32,
    /// Background colour as r,g,b in [0, 1].
    #[arg(long, default_value = "0,0,0", value_parser = parse_vec3)]
    background: [f32; 3],
    /// Orbit centre as x,y,z.
    #[arg(long, default_value = "0,0,0", value_parser = parse_vec3, allow_hyphen_values = true)]
    center: [f32; 3],
    /// The world's up axis: y, -y (COLMAP scenes), z or -z.
    #[arg(long, default_value = "y", allow_hyphen_values = true)]
    up: String,
    /// Skip the depth EXRs.
    #[arg(long)]
    no_depth: bool,
    /// Also write the frames as an animated GIF (`orbit.gif`: a turntable with the default
    /// orbit), each frame shown this many milliseconds.
    #[arg(long, value_name = "MS", num_args = 0..=1, default_missing_value = "80")]
    gif: Option<u32>,
    /// Render one frame from a camera of this dataset scene (its cameras.json) instead of the
    /// orbit, at that camera's resolution and intrinsics (--view picks it).
    #[arg(long)]
    scene: Option<PathBuf>,
    /// With --scene: the camera, counting the scene's input views first, then its supervision
    /// views (the order `velox view` lists them in).
    #[arg(long, default_value_t = 0, requires = "scene")]
    view: usize,
}

pub fn parse_vec3(s: &str) -> Result<[f32; 3], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|x| x.trim().parse::<f32>().map_err(|_| format!("`{x}` is not a number")))
        .collect::<Result<_, _>>()?;
    <[f32; 3]>::try_from(v).map_err(|_| format!("expected three comma-separated numbers, got `{s}`"))
}

#[derive(Serialize)]
struct Frame {
    index: u32,
    png: String,
    depth_exr: Option<String>,
    eye: [f32; 3],
    camera: Camera,
    drawn: u32,
    invalid: u32,
    behind_near_plane: u32,
    too_faint: u32,
    outside_image: u32,
    too_many_tiles: u32,
    tile_pairs: u64,
}

/// The camera of frame `i` of `frames` on the orbit.
fn orbit_camera(a: &RenderArgs, i: u32) -> CliResult<Camera> {
    // (up, two horizontal axes) of the world.
    let (up, h1, h2): ([f32; 3], [f32; 3], [f32; 3]) = match a.up.as_str() {
        "y" => ([0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]),
        "-y" => ([0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]),
        "z" => ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
        "-z" => ([0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]),
        other => return Err(format!("--up {other}: expected y, -y, z or -z").into()),
    };
    let az = std::f32::consts::TAU * i as f32 / a.frames as f32;
    let el = a.elevation.to_radians();
    let dir: [f32; 3] =
        [0, 1, 2].map(|k| el.cos() * (az.cos() * h1[k] + az.sin() * h2[k]) + el.sin() * up[k]);
    let eye = [0, 1, 2].map(|k| a.center[k] + a.radius * dir[k]);
    Ok(Camera::look_at(eye, a.center, up, a.fov, a.width, a.height))
}

pub fn run(a: &RenderArgs) -> CliResult<()> {
    let sound = a.fov > 0.0 && a.fov < 180.0 && a.radius > 0.0;
    if !sound {
        return Err(format!(
            "--fov must be in (0, 180) and --radius positive, got {} and {}",
            a.fov, a.radius
        )
        .into());
    }
    let cameras: Vec<Camera> = match &a.scene {
        Some(scene) => vec![scene_camera(scene, a.view)?],
        None => (0..a.frames).map(|i| orbit_camera(a, i)).collect::<CliResult<_>>()?,
    };
    let (data, sh) = ply::read_sh(&a.ply)?;
    std::fs::create_dir_all(&a.out).map_err(|e| format!("creating {}: {e}", a.out.display()))?;
    let gpu = Gpu::new()?;
    let gaussians = data.upload(&gpu)?;
    // Higher spherical harmonics (f_rest_*) colour each Gaussian along each view.
    let harmonics = match &sh {
        Some(sh) => Some((Tensor::from_slice(&gpu, &[data.len(), sh.stride()], &sh.coeffs)?, sh.degree)),
        None => None,
    };
    println!(
        "rendering {} Gaussians from {}{} to {} frames of {}x{} on {}",
        data.len(),
        a.ply.display(),
        sh.as_ref().map_or(String::new(), |sh| format!(" (spherical harmonics of degree {})", sh.degree)),
        cameras.len(),
        cameras[0].width,
        cameras[0].height,
        gpu.caps().name
    );
    let bar = ProgressBar::new(cameras.len() as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames, {elapsed} elapsed, {eta} left")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut frames = Vec::new();
    let mut images = Vec::new();
    for (i, &cam) in (0u32..).zip(&cameras) {
        let r = render_view(&gpu, &gaussians, harmonics.as_ref().map(|(t, d)| (t, *d)), &cam, a.background)?;
        let stats = r.stats()?;
        let rgb: Vec<f32> = r.image.rgb.read()?;
        let png = a.out.join(format!("frame_{i:04}.png"));
        image::write_png(&png, &rgb, cam.width, cam.height)?;
        if a.gif.is_some() {
            images.push(rgb);
        }
        let depth_exr = if a.no_depth {
            None
        } else {
            // Depth of the covered part: the blended depth over the alpha (0 where nothing is).
            let depth: Vec<f32> = r.image.depth.read()?;
            let alpha: Vec<f32> = r.image.alpha.read()?;
            let z: Vec<f32> =
                depth.iter().zip(&alpha).map(|(&d, &a)| if a > 1.0 / 255.0 { d / a } else { 0.0 }).collect();
            let path = a.out.join(format!("depth_{i:04}.exr"));
            image::write_exr_depth(&path, &z, cam.width, cam.height)?;
            Some(name(&path))
        };
        let eye = cam.centre();
        frames.push(Frame {
            index: i,
            png: name(&png),
            depth_exr,
            eye,
            camera: cam,
            drawn: stats.drawn,
            invalid: stats.invalid,
            behind_near_plane: stats.behind_near_plane,
            too_faint: stats.too_faint,
            outside_image: stats.outside_image,
            too_many_tiles: stats.too_many_tiles,
            tile_pairs: stats.intersections,
        });
        bar.inc(1);
    }
    bar.finish();
    let json = a.out.join("render.json");
    write_bytes(&json, serde_json::to_string_pretty(&frames)?.as_bytes())?;
    if let Some(delay) = a.gif {
        let (w, h) = (cameras[0].width, cameras[0].height);
        image::write_gif(&a.out.join("orbit.gif"), &images, w, h, delay)?;
    }
    let dropped = frames.first().map(|f| f.invalid).unwrap_or(0);
    if dropped > 0 {
        println!("{dropped} Gaussians have NaN, Inf or degenerate parameters and were not drawn");
    }
    println!("wrote {} frames to {} (render.json lists them)", frames.len(), a.out.display());
    Ok(())
}

/// Camera `view` of a scene's cameras.json: its input views, then its supervision views.
fn scene_camera(scene: &Path, view: usize) -> CliResult<Camera> {
    let cameras = velox_tasks::view::scene_cameras(scene)?;
    let count = cameras.len();
    cameras.get(view).map(|c| c.camera).ok_or_else(|| {
        format!(
            "--view {view}: {} has {count} cameras (input, then supervision views)",
            scene.join("cameras.json").display()
        )
        .into()
    })
}

fn name(p: &Path) -> String {
    p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use clap::Parser;
    use velox_engine::ops::raster::GaussianData;

    use super::*;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: RenderArgs,
    }

    #[test]
    fn renders_an_orbit_to_png_exr_and_json() {
        let dir = std::env::temp_dir().join(format!("velox-render-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut g = GaussianData::benchmark_scene(500, 3);
        // Centre the scene on the origin, where the orbit looks.
        g.means.iter_mut().skip(2).step_by(3).for_each(|z| *z -= 3.0);
        let ply_path = dir.join("scene.ply");
        ply::write(&ply_path, &g).unwrap();
        let out = dir.join("frames");
        let argv = [
            "velox-render",
            ply_path.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--frames",
            "2",
            "--width",
            "40",
            "--height",
            "24",
            "--elevation",
            "-10",
            "--background",
            "1,1,1",
            "--up",
            "-y",
            "--gif",
        ];
        let cli = Cli::try_parse_from(argv).unwrap();
        run(&cli.args).unwrap();
        let (rgb, w, h) = image::read_png(&out.join("frame_0001.png")).unwrap();
        assert_eq!((w, h, rgb.len()), (40, 24, 40 * 24 * 3));
        assert!(rgb.iter().any(|&v| v < 0.9), "something is drawn over the white background");
        let (z, _, _) = image::read_exr_depth(&out.join("depth_0000.exr")).unwrap();
        assert!(z.iter().any(|&d| d > 2.0 && d < 6.0), "depths near the orbit radius");
        let frames: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("render.json")).unwrap()).unwrap();
        assert_eq!(frames.as_array().unwrap().len(), 2);
        let gif = image::read_gif(&out.join("orbit.gif")).unwrap();
        assert_eq!((gif.frames.len(), gif.width, gif.height, gif.delays_ms), (2, 40, 24, vec![80, 80]));
        // render.json records the camera of every frame.
        let cam: Camera = serde_json::from_value(frames[1]["camera"].clone()).unwrap();
        assert_eq!((cam.width, cam.height), (40, 24));
        assert!(Cli::try_parse_from(["velox-render", "x.ply", "--background", "1,2"]).is_err());
        assert!(
            Cli::try_parse_from(["velox-render", "x.ply", "--view", "2"]).is_err(),
            "--view needs --scene"
        );
    }
}
