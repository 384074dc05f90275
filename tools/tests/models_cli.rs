//! The model commands as a user meets them, on a tiny scene and a tiny autoencoder trained a
//! few steps in-process: `decode points`, `decode gaussians`, `eval recon`, `encode`, `config
//! --params`, `bench models`, `bench train`, and their errors.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use velox_data::format::write_scene;
use velox_data::{procedural, read_scene, SynthOptions};
use velox_engine::rng::Rng;
use velox_engine::Gpu;
use velox_io::ply;
use velox_models::config::AutoencoderConfig;
use velox_models::velox::autoencoder::Autoencoder;
use velox_models::Model;
use velox_tasks::training::train_scene;

fn velox(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_velox")).args(args).output().unwrap()
}

fn ok(out: &Output) -> String {
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    stdout
}

fn fails(out: &Output) -> String {
    assert!(!out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!err.contains("panicked"), "{err}");
    err
}

/// One tiny scene (`DIR/data/scene_00000`, 32 px, 4000 points) and a tiny autoencoder trained
/// on it for a few steps (`DIR/ae.safetensors`), made once for every test of this file.
fn fixture() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("velox-models-cli-{}", std::process::id()));
        let scene_dir = dir.join("data").join("scene_00000");
        let gpu = Gpu::new().unwrap();
        let (_, mesh) = procedural::scene(3, None).unwrap();
        let opts = SynthOptions { res: 32, points: 4000, supersample: 1, tracks: 8, ..Default::default() };
        write_scene(&gpu, &mesh, "test", None, 3, &opts, &scene_dir, &mut |_| {}).unwrap();
        let scene = train_scene(&gpu, &read_scene(&scene_dir, true).unwrap()).unwrap();
        let mut ae = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 1).unwrap();
        let mut rng = Rng::new(2);
        for step in 1..=5 {
            ae.train_step(&scene, step, &mut rng).unwrap();
        }
        ae.save(&dir.join("ae.safetensors")).unwrap();
        dir
    })
}

fn arg(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The vertex count and the body of a binary PLY.
fn ply_vertices(path: &Path) -> (String, usize, usize) {
    let bytes = std::fs::read(path).unwrap();
    let end = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let header = String::from_utf8(bytes[..end].to_vec()).unwrap();
    let n = header.lines().find_map(|l| l.strip_prefix("element vertex ")).unwrap().parse().unwrap();
    (header, n, bytes.len() - end)
}

#[test]
fn decode_points_writes_a_cloud_per_frame() {
    let dir = fixture();
    let out = dir.join("points");
    let scene = dir.join("data/scene_00000");
    let ckpt = dir.join("ae.safetensors");
    let args = ["decode", "points", "--checkpoint", arg(&ckpt), "--cloud", arg(&scene)];
    let text = ok(&velox(
        &[&args[..], &["--out", arg(&out), "--frames", "0,5", "--points", "300", "--steps", "3"]].concat(),
    ));
    assert!(text.contains("wrote 2 files"), "{text}");
    for f in [0, 5] {
        let (header, n, body) = ply_vertices(&out.join(format!("points_f{f:02}.ply")));
        assert!(header.contains("property float tau"), "{header}");
        assert_eq!((n, body), (300, 300 * 16));
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("decode.json")).unwrap()).unwrap();
    assert_eq!(report["frames"].as_array().unwrap().len(), 2);
    // A PLY of x y z r g b tau is accepted as well as a scene folder; Euler too.
    let cloud = scene.join("points.ply");
    let args = ["decode", "points", "--checkpoint", arg(&ckpt), "--cloud", arg(&cloud)];
    let euler = dir.join("points_euler");
    let rest =
        ["--out", arg(&euler), "--frames", "23", "--points", "64", "--steps", "2", "--sampler", "euler"];
    ok(&velox(&[&args[..], &rest[..]].concat()));
    assert_eq!(ply_vertices(&euler.join("points_f23.ply")).1, 64);

    // A video folder as `velox import rgbd` writes it (RGBD frames and camera.json): its
    // frames are back-projected into the cloud that is encoded. The scene's own video, with
    // its camera beside it, is one.
    let video = dir.join("video_folder");
    std::fs::create_dir_all(&video).unwrap();
    for entry in std::fs::read_dir(scene.join("video")).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), video.join(entry.file_name())).unwrap();
    }
    let cameras: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("cameras.json")).unwrap()).unwrap();
    std::fs::write(video.join("camera.json"), cameras["video"].to_string()).unwrap();
    let from_video = dir.join("points_video");
    let args = ["decode", "points", "--checkpoint", arg(&ckpt), "--cloud", arg(&video)];
    let rest = ["--out", arg(&from_video), "--frames", "3", "--points", "64", "--steps", "2"];
    let text = ok(&velox(&[&args[..], &rest[..]].concat()));
    assert!(text.contains("wrote 1 file"), "{text}");
    assert_eq!(ply_vertices(&from_video.join("points_f03.ply")).1, 64);
    // A capture imported in windows (frames 0 to 23 and 16 to 39, the same video in both
    // here) is decoded window by window, its frames named by the capture's: frame 30 is the
    // second window's frame 14, as that window alone decodes it.
    let windowed = dir.join("windowed");
    let mut record = velox_data::capture::CaptureRecord {
        source: arg(&video).into(),
        source_frames: 40,
        fps: None,
        windows: Vec::new(),
        centre: [0.0; 3],
        scale: 1.0,
        depth_pixels: 1,
        dropped_beyond_max_depth: 0,
    };
    for (k, first) in [0usize, 16].into_iter().enumerate() {
        let w = format!("window_{k:03}");
        std::fs::create_dir_all(windowed.join(&w)).unwrap();
        for entry in std::fs::read_dir(&video).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), windowed.join(&w).join(entry.file_name())).unwrap();
        }
        let frames: Vec<usize> = (first..first + 24).collect();
        let files = |kind: &str| frames.iter().map(|f| format!("{kind}{f}")).collect();
        record.windows.push(velox_data::capture::CaptureWindow {
            dir: w,
            frames: frames.clone(),
            colour_files: files("colour"),
            depth_files: files("depth"),
            times: None,
        });
    }
    std::fs::write(windowed.join("capture.json"), serde_json::to_string(&record).unwrap()).unwrap();
    let stitched = dir.join("points_windowed");
    let args = ["decode", "points", "--checkpoint", arg(&ckpt), "--cloud", arg(&windowed)];
    let rest = ["--out", arg(&stitched), "--frames", "3,30", "--points", "64", "--steps", "2"];
    let text = ok(&velox(&[&args[..], &rest[..]].concat()));
    assert!(
        text.contains("2 windows of 24 frames, 2 of them encoded") && text.contains("wrote 2 files"),
        "{text}"
    );
    assert_eq!(
        std::fs::read(stitched.join("points_f03.ply")).unwrap(),
        std::fs::read(from_video.join("points_f03.ply")).unwrap()
    );
    let alone = dir.join("points_window_001");
    let second = windowed.join("window_001");
    let args = ["decode", "points", "--checkpoint", arg(&ckpt), "--cloud", arg(&second)];
    let rest = ["--out", arg(&alone), "--frames", "14", "--points", "64", "--steps", "2"];
    ok(&velox(&[&args[..], &rest[..]].concat()));
    assert_eq!(
        std::fs::read(stitched.join("points_f30.ply")).unwrap(),
        std::fs::read(alone.join("points_f14.ply")).unwrap()
    );
    let report = velox_io::decoded::DecodeReport::read(&stitched).unwrap();
    let frames: Vec<(usize, &str)> = report.frames.iter().map(|f| (f.frame, f.file.as_str())).collect();
    assert_eq!(frames, [(3, "points_f03.ply"), (30, "points_f30.ply")]);
    // Frames past the capture's are refused naming its range.
    let args = ["decode", "points", "--checkpoint", arg(&ckpt), "--cloud", arg(&windowed)];
    let out = velox(&[&args[..], &["--out", arg(&stitched), "--frames", "40"][..]].concat());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("frame 40 is out of range: the clip has frames 0 to 39"),
        "{err}"
    );
}

#[test]
fn decode_mesh_writes_a_surface_per_frame_in_every_format() {
    let dir = fixture();
    let out = dir.join("mesh");
    let (scene, ckpt) = (dir.join("data/scene_00000"), dir.join("ae.safetensors"));
    let args = ["decode", "mesh", "--checkpoint", arg(&ckpt), "--cloud", arg(&scene), "--out", arg(&out)];
    let rest = ["--frames", "0,5", "--points", "2000", "--steps", "3", "--resolution", "24"];
    let text = ok(&velox(&[&args[..], &rest[..]].concat()));
    assert!(text.contains("wrote 6 files"), "{text}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("decode.json")).unwrap()).unwrap();
    assert_eq!(report["command"], "decode mesh");
    for (k, f) in [0, 5].into_iter().enumerate() {
        let ply = velox_io::mesh::read(&out.join(format!("mesh_f{f:02}.ply"))).unwrap();
        assert!(!ply.triangles.is_empty());
        assert_eq!(report["frames"][k]["count"].as_u64().unwrap() as usize, ply.triangles.len());
        // The same mesh in every format: OBJ's decimals give back the f32s.
        for ext in ["obj", "glb"] {
            assert_eq!(velox_io::mesh::read(&out.join(format!("mesh_f{f:02}.{ext}"))).unwrap(), ply, "{ext}");
        }
    }
    // A scene named from another folder is recorded absolutely: the viewer finds it anywhere.
    let relative = std::process::Command::new(env!("CARGO_BIN_EXE_velox"))
        .current_dir(dir)
        .args([
            "decode",
            "mesh",
            "--checkpoint",
            arg(&ckpt),
            "--cloud",
            "data/scene_00000",
            "--out",
            "mesh_rel",
        ])
        .args(["--frames", "1", "--points", "500", "--steps", "2", "--format", "ply"])
        .output()
        .unwrap();
    ok(&relative);
    let report = velox_io::decoded::DecodeReport::read(&dir.join("mesh_rel")).unwrap();
    assert_eq!(report.scene(), Some(scene.clone()), "{}", report.cloud);
    // One format on request; a resolution out of range is refused before any work.
    let obj = dir.join("mesh_obj");
    let rest = ["--frames", "2", "--points", "500", "--steps", "2", "--format", "obj", "--out", arg(&obj)];
    ok(&velox(&[&args[..6], &rest[..]].concat()));
    let names: Vec<String> = std::fs::read_dir(&obj)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        names.contains(&"mesh_f02.obj".to_string()) && !names.iter().any(|n| n.ends_with(".ply")),
        "{names:?}"
    );
    let err = fails(&velox(&[&args[..], &["--resolution", "4"][..]].concat()));
    assert!(err.contains("--resolution 4"), "{err}");
}

#[test]
fn decode_gaussians_writes_splat_files_from_surface_or_cloud_voxels() {
    let dir = fixture();
    let ckpt = dir.join("ae.safetensors");
    let scene = dir.join("data/scene_00000");
    // The cloud's voxels in f16, to run the CLI's f16 path too.
    for (voxels, precision) in [("surface", "f32"), ("cloud", "f16")] {
        let out = dir.join(format!("gaussians_{voxels}"));
        let args =
            ["decode", "gaussians", "--checkpoint", arg(&ckpt), "--cloud", arg(&scene), "--out", arg(&out)];
        let rest = [
            "--frames",
            "3",
            "--voxels",
            voxels,
            "--points",
            "512",
            "--steps",
            "3",
            "--precision",
            precision,
        ];
        ok(&velox(&[&args[..], &rest[..]].concat()));
        let g = ply::read(&out.join("gaussians_f03.ply")).unwrap();
        // The tiny config decodes 4 Gaussians per voxel.
        assert!(!g.is_empty() && g.len().is_multiple_of(4), "{} Gaussians", g.len());
        assert!(g.means.iter().all(|v| v.is_finite()));
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("decode.json")).unwrap()).unwrap();
        assert_eq!(report["frames"][0]["voxels"].as_u64().unwrap() * 4, g.len() as u64);
        assert_eq!(report["precision"], precision);
    }
    // Two frames as a clip beside the truth; a cloud without a scene's cameras is refused.
    let out = dir.join("gaussians_clip");
    let args =
        ["decode", "gaussians", "--checkpoint", arg(&ckpt), "--cloud", arg(&scene), "--out", arg(&out)];
    ok(&velox(&[&args[..], &["--frames", "3,9", "--voxels", "cloud", "--gif"][..]].concat()));
    let gif = velox_io::image::read_gif(&out.join("clip.gif")).unwrap();
    assert_eq!((gif.frames.len(), gif.width), (2, 2 * gif.height));
    let (png, w, h) = velox_io::image::read_png(&out.join("clip/f09.png")).unwrap();
    // The GIF enlarges the views by a whole factor to at least 256 px; the PNG keeps their size.
    let k = gif.width / w;
    assert!(k * w == gif.width && gif.width >= 256 && (k - 1) * w < 256, "{} from {w}", gif.width);
    // The GIF's frame is the PNG enlarged and quantised to a palette of 256 colours.
    let (w, k) = (w as usize, k as usize);
    let png: Vec<f32> = (0..h as usize * k)
        .flat_map(|y| (0..w * k).flat_map(move |x| [0, 1, 2].map(|c| 3 * ((y / k) * w + x / k) + c)))
        .map(|i| png[i])
        .collect();
    let mean = png.iter().zip(&gif.frames[1]).map(|(a, b)| (a - b).abs()).sum::<f32>() / png.len() as f32;
    assert!(mean <= 4.0 / 255.0, "the PNG is the frame: mean difference {mean}");
    let cloud = dir.join("cloud.ply");
    std::fs::copy(scene.join("points.ply"), &cloud).unwrap();
    let args =
        ["decode", "gaussians", "--checkpoint", arg(&ckpt), "--cloud", arg(&cloud), "--out", arg(&out)];
    let err = fails(&velox(&[&args[..], &["--gif"][..]].concat()));
    assert!(err.contains("--gif") && err.contains("dataset scene"), "{err}");
}

#[test]
fn eval_recon_reports_psnr_ssim_and_chamfer_per_scene_and_mean() {
    let dir = fixture();
    let out = dir.join("eval");
    let json = dir.join("eval.json");
    let (data, ckpt) = (dir.join("data"), dir.join("ae.safetensors"));
    let args = ["eval", "recon", "--data", arg(&data), "--checkpoint", arg(&ckpt)];
    let text = ok(&velox(
        &[
            &args[..],
            &[
                "--out",
                arg(&out),
                "--json",
                arg(&json),
                "--views",
                "2",
                "--frame-step",
                "8",
                "--points",
                "500",
                "--steps",
                "3",
                "--sampler",
                "euler",
            ],
        ]
        .concat(),
    ));
    assert!(text.contains("PSNR") && text.contains("mean"), "{text}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!((report["sampler"].as_str(), report["steps"].as_u64()), (Some("euler"), Some(3)));
    let scenes = report["scenes"].as_array().unwrap();
    assert_eq!(scenes.len(), 1);
    for m in [&scenes[0], &report["mean"]] {
        let (psnr, ssim, cd) =
            (m["psnr"].as_f64().unwrap(), m["ssim"].as_f64().unwrap(), m["chamfer"].as_f64().unwrap());
        assert!(psnr > 0.0 && psnr < 100.0, "psnr {psnr}");
        assert!(ssim > -1.0 && ssim <= 1.0, "ssim {ssim}");
        assert!(cd > 0.0 && cd.is_finite(), "chamfer {cd}");
    }
    // Frames 0, 8 and 16, two views each.
    let frames = scenes[0]["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 3);
    assert_eq!(frames[0]["views"].as_array().unwrap().len(), 2);
    let images = scenes[0]["images"].as_array().unwrap();
    assert_eq!(images.len(), 4);
    let (rgb, w, h) = velox_io::image::read_png(&out.join(images[0].as_str().unwrap())).unwrap();
    assert_eq!((w, h, rgb.len()), (64, 32, 64 * 32 * 3), "ground truth | ours, side by side");
}

#[test]
fn bad_checkpoints_clouds_and_frames_get_clear_errors() {
    let dir = fixture();
    let scene = dir.join("data/scene_00000");
    let ckpt = dir.join("ae.safetensors");
    let decode = |ckpt: &Path, cloud: &Path, frames: &str| {
        velox(&[
            "decode",
            "points",
            "--checkpoint",
            arg(ckpt),
            "--cloud",
            arg(cloud),
            "--out",
            arg(&dir.join("bad")),
            "--frames",
            frames,
            "--points",
            "64",
            "--steps",
            "1",
        ])
    };
    let err = fails(&decode(&dir.join("missing.safetensors"), &scene, "0"));
    assert!(err.contains("cannot read") && err.contains("missing.safetensors"), "{err}");
    let corrupt = dir.join("corrupt.safetensors");
    std::fs::write(&corrupt, b"not a checkpoint").unwrap();
    let err = fails(&decode(&corrupt, &scene, "0"));
    assert!(err.contains("corrupt"), "{err}");
    let err = fails(&decode(&ckpt, &scene, "0,99"));
    assert!(err.contains("frame 99 is out of range"), "{err}");
    // A cloud with a point outside [-1, 1]^3.
    let mut points = velox_data::format::read_ply(&scene.join("points.ply")).unwrap();
    points[7][0] = 3.0;
    let far = dir.join("far.ply");
    velox_data::format::write_ply(&far, &points).unwrap();
    let err = fails(&decode(&ckpt, &far, "0"));
    assert!(err.contains("point 7") && err.contains("outside [-1, 1]^3"), "{err}");
    let err = fails(&decode(&ckpt, &dir.join("nothing.ply"), "0"));
    assert!(err.contains("nothing.ply"), "{err}");
    let err = fails(&velox(&["eval", "recon", "--data", arg(&dir.join("bad")), "--checkpoint", arg(&ckpt)]));
    assert!(err.contains("bad"), "{err}");
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

#[test]
fn encode_stores_tokens_beside_the_scenes_keeps_them_and_refuses_another_checkpoint() {
    let dir = std::env::temp_dir().join(format!("velox-encode-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let data = dir.join("data");
    copy_dir(&fixture().join("data/scene_00000"), &data.join("scene_00000"));
    let ckpt = fixture().join("ae.safetensors");
    let encode = |ckpt: &Path, rest: &[&str]| {
        velox(&[&["encode", "--checkpoint", arg(ckpt), "--data", arg(&data)], rest].concat())
    };
    // Beside the scenes by default.
    let text = ok(&encode(&ckpt, &[]));
    assert!(text.contains("encoded 1 scenes (4000 points)") && text.contains("kept 0"), "{text}");
    assert!(text.contains("token statistics per channel"), "{text}");
    let tokens = data.join("tokens");
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(tokens.join("tokens.json")).unwrap()).unwrap();
    assert_eq!(manifest["scenes"], serde_json::json!(["scene_00000"]));
    assert_eq!((manifest["tokens"].as_u64(), manifest["token_dim"].as_u64()), (Some(32), Some(8)));
    assert_eq!(manifest["mean"].as_array().unwrap().len(), 8);
    let stored = std::fs::read(tokens.join("scene_00000.safetensors")).unwrap();
    // The token folder is no scene to the commands that list a dataset's scenes.
    assert_eq!(velox_data::format::list_scenes(&data).unwrap(), [data.join("scene_00000")]);
    // Again: kept.
    let text = ok(&encode(&ckpt, &[]));
    assert!(text.contains("encoded 0 scenes") && text.contains("kept 1"), "{text}");
    assert_eq!(std::fs::read(tokens.join("scene_00000.safetensors")).unwrap(), stored);
    // Another checkpoint: refused without --force, saying so; replaced with it.
    let other = dir.join("other.safetensors");
    Autoencoder::new(&Gpu::new().unwrap(), &AutoencoderConfig::tiny(), 9).unwrap().save(&other).unwrap();
    let err = fails(&encode(&other, &[]));
    assert!(
        err.contains("ae.safetensors") && err.contains("other.safetensors") && err.contains("--force"),
        "{err}"
    );
    let text = ok(&encode(&other, &["--force", "--seed", "3", "--precision", "f16"]));
    assert!(text.contains("replaced what") && text.contains("encoded 1 scenes"), "{text}");
    assert_ne!(std::fs::read(tokens.join("scene_00000.safetensors")).unwrap(), stored);
    // Elsewhere with --out; nothing to encode is an error.
    let out = dir.join("elsewhere");
    ok(&encode(&ckpt, &["--out", arg(&out)]));
    assert_eq!(std::fs::read(out.join("scene_00000.safetensors")).unwrap(), stored);
    let err = fails(&velox(&["encode", "--checkpoint", arg(&ckpt), "--data", arg(&dir.join("none"))]));
    assert!(err.contains("none"), "{err}");
    std::fs::create_dir_all(dir.join("empty")).unwrap();
    let err = fails(&velox(&["encode", "--checkpoint", arg(&ckpt), "--data", arg(&dir.join("empty"))]));
    assert!(err.contains("holds no scenes"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The cases found in review: a scene whose meta.json says 0 supervision views made eval
/// recon index past its images, and a checkpoint with one NaN weight evaluated to a Chamfer
/// distance of inf. Both are errors that name the file and the problem.
#[test]
fn eval_recon_refuses_scenes_without_views_and_checkpoints_with_nan() {
    let dir = std::env::temp_dir().join(format!("velox-eval-hostile-{}", std::process::id()));
    let scene = dir.join("data").join("scene_00000");
    copy_dir(&fixture().join("data/scene_00000"), &scene);
    let meta_path = scene.join("meta.json");
    let mut meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&meta_path).unwrap()).unwrap();
    meta["supervision_views"] = 0.into();
    std::fs::write(&meta_path, meta.to_string()).unwrap();
    let ckpt = fixture().join("ae.safetensors");
    let eval = |data: &Path, ckpt: &Path| {
        velox(&[
            "eval",
            "recon",
            "--data",
            arg(data),
            "--checkpoint",
            arg(ckpt),
            "--out",
            arg(&dir.join("eval")),
        ])
    };
    let err = fails(&eval(&dir.join("data"), &ckpt));
    assert!(err.contains(arg(&meta_path)) && err.contains("supervision_views is 0"), "{err}");

    // One NaN in the first parameter tensor's data.
    let mut bytes = std::fs::read(&ckpt).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let (name, tensor) = header.as_object().unwrap().iter().find(|(k, _)| k.starts_with("param/")).unwrap();
    let at = 8 + n + tensor["data_offsets"][0].as_u64().unwrap() as usize + 4;
    bytes[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let nan = dir.join("nan.safetensors");
    std::fs::write(&nan, &bytes).unwrap();
    let err = fails(&eval(fixture().join("data").as_path(), &nan));
    assert!(
        err.contains("nan.safetensors")
            && err.contains(&format!("{name:?}"))
            && err.contains("holds 1 NaN or Inf"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bench_models_writes_records() {
    let dir = std::env::temp_dir().join(format!("velox-bench-models-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("models.json");
    let text = ok(&velox(&["bench", "models", "--quick", "--repeats", "1", "--json", arg(&json)]));
    assert!(text.contains("387.66"), "the paper's figures are shown:\n{text}");
    let records: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let records = records.as_array().unwrap();
    for name in ["encoder", "gaussian decoder frame", "surface decoder heun 4", "surface decoder heun 20"] {
        let find = |precision: &str| {
            records
                .iter()
                .find(|r| r["name"] == name && r["precision"] == precision)
                .unwrap_or_else(|| panic!("no {precision} {name} record"))
        };
        let (r32, r16) = (find("f32"), find("f16"));
        for r in [r32, r16] {
            assert!(r["median_ms"].as_f64().unwrap() > 0.0, "{r}");
        }
        // Same input, same weights: the repeated f32 run agrees with the first.
        assert!(r32["error_over"].as_str().unwrap().contains("determinism"), "{r32}");
        assert!(r32["nmse"].as_f64().unwrap() < 1e-10, "{r32}");
        // The f16 path is measured against the f32 path: close, but not the same numbers.
        assert!(r16["error_over"].as_str().unwrap().contains("f32 path"), "{r16}");
        let e = r16["nmse"].as_f64().unwrap();
        assert!(e > 0.0 && e < 1e-3, "{r16}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// The xyz rows of a decoded points PLY (float x y z tau).
fn decoded_points(path: &Path) -> Vec<[f32; 3]> {
    let bytes = std::fs::read(path).unwrap();
    let body = &bytes[bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11..];
    let f = |b: &[u8]| f32::from_le_bytes(b.try_into().unwrap());
    body.chunks(16).map(|p| [f(&p[0..4]), f(&p[4..8]), f(&p[8..12])]).collect()
}

#[test]
fn decode_and_eval_sample_a_frame_with_the_same_seed() {
    use velox_models::metrics::{chamfer, subsample};
    use velox_models::velox::decode::frame_points;

    // One seed rule for both: eval's Chamfer distance of frame 8 is the one of the points
    // `decode points` writes for frame 8 with the same seed and sampler.
    let dir = fixture();
    let (scene, ckpt) = (dir.join("data/scene_00000"), dir.join("ae.safetensors"));
    let sampling = ["--points", "500", "--steps", "3", "--sampler", "euler", "--seed", "4"];
    let out = dir.join("same_seed_points");
    let args = ["decode", "points", "--checkpoint", arg(&ckpt), "--cloud", arg(&scene), "--out", arg(&out)];
    ok(&velox(&[&args[..], &["--frames", "8"], &sampling[..]].concat()));
    let json = dir.join("same_seed_eval.json");
    let (data, eval_out) = (dir.join("data"), dir.join("same_seed_eval"));
    let args = ["eval", "recon", "--data", arg(&data), "--checkpoint", arg(&ckpt), "--out", arg(&eval_out)];
    let rest = ["--json", arg(&json), "--frame-step", "8", "--views", "1"];
    ok(&velox(&[&args[..], &rest[..], &sampling[..]].concat()));
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let frame = &report["scenes"][0]["frames"][1];
    assert_eq!(frame["frame"], 8);
    let cloud: Vec<f32> =
        velox_data::format::read_ply(&scene.join("points.ply")).unwrap().iter().flatten().copied().collect();
    let truth: Vec<[f32; 3]> = frame_points(&cloud)[8].chunks(3).map(|p| [p[0], p[1], p[2]]).collect();
    let decoded = decoded_points(&out.join("points_f08.ply"));
    let cd = chamfer(&subsample(&decoded, 500), &subsample(&truth, 500));
    let logged = frame["chamfer"].as_f64().unwrap();
    assert!((cd - logged).abs() <= 1e-12 * logged, "decode's points give {cd}, eval logged {logged}");
    // Another seed samples other points.
    let other = dir.join("other_seed_points");
    let args = ["decode", "points", "--checkpoint", arg(&ckpt), "--cloud", arg(&scene), "--out", arg(&other)];
    ok(&velox(&[&args[..], &["--frames", "8"], &sampling[..6], &["--seed", "5"]].concat()));
    assert_ne!(decoded_points(&other.join("points_f08.ply")), decoded);
}

/// The counts `velox config NAME --params` prints: encoder, surface, Gaussian decoder, total.
fn printed_counts(name: &str) -> Vec<usize> {
    printed_parts(&["config", name, "--params"], &["encoder", "surface decoder", "Gaussian decoder", "total"])
}

/// The counts of `parts` that `velox ARGS` prints, one line each.
fn printed_parts(args: &[&str], parts: &[&str]) -> Vec<usize> {
    let text = ok(&velox(args));
    parts
        .iter()
        .map(|part| {
            let line =
                text.lines().find(|l| l.trim_start().starts_with(part)).unwrap_or_else(|| panic!("{text}"));
            line[part.len() + 2..].split_whitespace().next().unwrap().replace(',', "").parse().unwrap()
        })
        .collect()
}

#[test]
fn config_params_counts_each_part_of_a_named_config_or_a_checkpoint() {
    let gpu = Gpu::new().unwrap();
    let ckpt = fixture().join("ae.safetensors");
    let built = Autoencoder::load(&gpu, &ckpt).unwrap().store.num_parameters();
    for name in ["tiny", arg(&ckpt)] {
        let c = printed_counts(name);
        assert_eq!(c[0] + c[1] + c[2], c[3], "{name}: {c:?}");
        assert_eq!(c[3], built, "{name}: the total is the store's");
        assert!(c[..3].iter().all(|&n| n > 0), "{c:?}");
    }
    // The paper's model is counted without allocating it.
    let paper = printed_counts("paper");
    assert!(paper[3] > 100_000_000, "{paper:?}");
    let err = fails(&velox(&["config", "no-such-config", "--params"]));
    assert!(err.contains("paper, small or tiny"), "{err}");
    // The voxel decoder's paper config: about 65 M, as the paper counts.
    let c = printed_parts(
        &["config", "paper", "--model", "voxels", "--params"],
        &["coarse stage", "fine stage", "total"],
    );
    assert_eq!(c[0] + c[1], c[2], "{c:?}");
    assert!((c[2] as f64 / 65e6 - 1.0).abs() < 0.05, "{c:?}");
}

#[test]
fn bench_train_reports_samples_per_second_the_time_split_dispatches_and_memory() {
    let dir = std::env::temp_dir().join(format!("velox-bench-train-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("train.json");
    let args = ["bench", "train", "--quick", "--repeats", "1", "--config", "tiny", "--batches", "1,2"];
    let text = ok(&velox(&[&args[..], &["--json", arg(&json)]].concat()));
    assert!(
        text.contains("samples/s") && text.contains("optimiser ms") && text.contains("GPU ms by family"),
        "{text}"
    );
    let records: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let records = records.as_array().unwrap();
    assert_eq!(records.len(), 4, "two precisions x two batches");
    for (r, (precision, batch)) in records.iter().zip([("f32", 1), ("f32", 2), ("f16", 1), ("f16", 2)]) {
        assert_eq!(r["shape"], format!("tiny config, batch {batch}"));
        assert_eq!(r["precision"], precision);
        assert!(r["dispatches_per_step"].as_u64().unwrap() > 50, "{r}");
        // A step submits at least once (each submit a host wait), and far fewer times than it
        // dispatches.
        let submits = r["submits_per_step"].as_u64().unwrap();
        assert!(submits >= 1 && submits * 20 < r["dispatches_per_step"].as_u64().unwrap(), "{r}");
        assert!(r["peak_memory_bytes"].as_u64().unwrap() > 1 << 20, "{r}");
        let families = r["family_ms"].as_object().unwrap();
        for family in ["matmul", "attention", "norm", "raster", "optimiser"] {
            assert!(families[family].as_f64().unwrap() > 0.0, "{family} in {r}");
        }
        assert_eq!(families.contains_key("cast"), precision == "f16", "f16 passes round their operands: {r}");
        assert_eq!(r["throughput_unit"], "samples/s");
        assert!(r["throughput"].as_f64().unwrap() > 0.0, "{r}");
        let split = &r["time_split_ms"];
        for part in ["data", "compute", "all_reduce", "optimiser"] {
            assert!(split[part].as_f64().unwrap() >= 0.0, "{r}");
        }
        assert!(split["compute"].as_f64().unwrap() > 0.0, "{r}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bench_train_times_a_model_downstream_of_the_encoder() {
    let dir = std::env::temp_dir().join(format!("velox-bench-train-tracker-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("tracker.json");
    let args = ["bench", "train", "--model", "tracker", "--quick", "--repeats", "1", "--config", "tiny"];
    let text = ok(&velox(&[&args[..], &["--json", arg(&json)]].concat()));
    assert!(text.contains("GPU ms by family"), "{text}");
    let records: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let records = records.as_array().unwrap();
    assert_eq!(records.len(), 2, "f32 and f16");
    for (r, precision) in records.iter().zip(["f32", "f16"]) {
        assert_eq!(r["precision"], precision);
        assert!(r["shape"].as_str().unwrap().starts_with("tiny tracker config"), "{r}");
        assert!(r["throughput"].as_f64().unwrap() > 0.0, "{r}");
        assert!(r["dispatches_per_step"].as_u64().unwrap() > 10, "{r}");
        assert!(r["family_ms"]["matmul"].as_f64().unwrap() > 0.0, "{r}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn voxels_train_evaluate_and_feed_the_gaussian_decoder() {
    // The voxel decoder's commands end to end on the fixture: encode, train a few steps,
    // evaluate against the occupancy, and decode Gaussians and evaluate images from its
    // predicted voxels beside the input's.
    let dir = fixture();
    let work = dir.join("voxels");
    let data = work.join("data");
    copy_dir(&dir.join("data"), &data);
    let ckpt = dir.join("ae.safetensors");
    ok(&velox(&["encode", "--checkpoint", arg(&ckpt), "--data", arg(&data)]));
    let run = work.join("run");
    let said = ok(&velox(&[
        "train",
        "voxels",
        "--data",
        arg(&data),
        "--config",
        "tiny",
        "--out",
        arg(&run),
        "--steps",
        "2",
    ]));
    assert!(said.contains("trained 2 steps"), "{said}");
    let vox = run.join("checkpoint.safetensors");
    // The checkpoint says it holds a voxel decoder: its config and count need no --model.
    let counted = printed_parts(&["config", arg(&vox), "--params"], &["total"])[0];
    let gpu = Gpu::new().unwrap();
    assert_eq!(
        counted,
        velox_models::velox::voxels::VoxelDecoder::load(&gpu, &vox).unwrap().store.num_parameters()
    );
    let log = std::fs::read_to_string(run.join("log.jsonl")).unwrap();
    assert!(log.contains("\"coarse\"") && log.contains("\"fine\""), "{log}");

    let ev = work.join("eval");
    let said = ok(&velox(&[
        "eval",
        "voxels",
        "--data",
        arg(&data),
        "--checkpoint",
        arg(&vox),
        "--out",
        arg(&ev),
        "--frame-step",
        "12",
    ]));
    assert!(said.contains("IoU") && said.contains("scene_00000"), "{said}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(ev.join("voxels.json")).unwrap()).unwrap();
    let frames = report["scenes"][0]["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 2, "frames 0 and 12");
    for f in frames {
        let m = &f["metrics"];
        assert!(m["true_voxels"].as_f64().unwrap() > 0.0, "{m}");
        for k in ["accuracy", "precision", "recall", "iou"] {
            let v = m[k].as_f64().unwrap();
            assert!((0.0..=1.0).contains(&v), "{k} {v}");
        }
    }
    assert!(ev.join("scene_00000/f00_xyz.png").is_file());

    // eval recon: predicted voxels beside the input's, both measured.
    let er = work.join("recon");
    let said = ok(&velox(&[
        "eval",
        "recon",
        "--data",
        arg(&data),
        "--checkpoint",
        arg(&ckpt),
        "--voxel-decoder",
        arg(&vox),
        "--out",
        arg(&er),
        "--frame-step",
        "12",
        "--views",
        "2",
        "--points",
        "300",
        "--steps",
        "2",
    ]));
    assert!(said.contains("predicted dB") && said.contains("input dB"), "{said}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(er.join("eval.json")).unwrap()).unwrap();
    let sources = report["mean"]["sources"].as_array().unwrap();
    assert_eq!(sources.len(), 2);
    assert_eq!(
        (sources[0]["source"].as_str(), sources[1]["source"].as_str()),
        (Some("predicted"), Some("input"))
    );

    // Predicted voxels need a voxel decoder; one trained on another autoencoder's tokens is
    // refused.
    let (scene, dec) = (data.join("scene_00000"), work.join("dec"));
    let args = ["decode", "gaussians", "--checkpoint", arg(&ckpt), "--cloud", arg(&scene)];
    let err = fails(&velox(&[&args[..], &["--out", arg(&dec), "--voxels", "predicted"]].concat()));
    assert!(err.contains("--voxel-decoder"), "{err}");
    let other = work.join("other.safetensors");
    let mut bytes = std::fs::read(&ckpt).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1; // another checkpoint: the same config, one weight's last bit
    std::fs::write(&other, &bytes).unwrap();
    let args = ["decode", "gaussians", "--checkpoint", arg(&other), "--cloud", arg(&scene)];
    let err = fails(&velox(&[&args[..], &["--out", arg(&dec), "--voxel-decoder", arg(&vox)]].concat()));
    assert!(err.contains("hash") && err.contains("other.safetensors"), "{err}");
}

#[test]
fn tracker_trains_evaluates_and_tracks_a_video() {
    // The tracker's commands end to end on the fixture: the videos' tokens, a few steps of
    // training, TAPVid-3D's metrics beside the baselines, and `velox track` on the scene's
    // video; tokens of the point clouds and a tracker of another encoder are refused.
    let dir = fixture();
    let work = dir.join("tracker");
    let data = work.join("data");
    copy_dir(&dir.join("data"), &data);
    let ckpt = dir.join("ae.safetensors");
    let run = work.join("run");
    let train = |tokens: Option<&Path>| {
        let mut args = vec!["train", "tracker", "--data", arg(&data), "--config", "tiny", "--out", arg(&run)];
        args.extend(["--steps", "2"]);
        if let Some(t) = tokens {
            args.extend(["--tokens", arg(t)]);
        }
        velox(&args)
    };
    // Tokens of the point clouds are not the tracker's.
    ok(&velox(&["encode", "--checkpoint", arg(&ckpt), "--data", arg(&data)]));
    let err = fails(&train(Some(&data.join("tokens"))));
    assert!(err.contains("points clouds") && err.contains("--source video"), "{err}");
    let said = ok(&velox(&["encode", "--checkpoint", arg(&ckpt), "--data", arg(&data), "--source", "video"]));
    assert!(said.contains("RGBD videos") && said.contains("tokens-video"), "{said}");
    let said = ok(&train(None));
    assert!(said.contains("trained 2 steps"), "{said}");
    let tracker = run.join("checkpoint.safetensors");
    let counted = printed_parts(&["config", arg(&tracker), "--params"], &["total"])[0];
    let gpu = Gpu::new().unwrap();
    assert_eq!(
        counted,
        velox_models::velox::tracker::Tracker::load(&gpu, &tracker).unwrap().store.num_parameters()
    );

    // `velox eval tracking` on the data and tracker above, with `extra` arguments.
    let eval = |extra: &[&str], out: &Path| {
        let mut args =
            vec!["eval", "tracking", "--data", arg(&data), "--checkpoint", arg(&tracker), "--out", arg(out)];
        args.extend_from_slice(extra);
        velox(&args)
    };
    let ev = work.join("eval");
    let said = ok(&eval(&[], &ev));
    assert!(said.contains("APD vis") && said.contains("static") && said.contains("truth"), "{said}");
    // The benchmark's protocol, said: its default scaling, thresholds in 256-pixel units.
    assert!(said.contains("rescaled by median") && said.contains("256-pixel short side"), "{said}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(ev.join("tracking.json")).unwrap()).unwrap();
    assert_eq!(report["scaling"], "median");
    assert_eq!(report["threshold_resolution"], 256);
    let none = work.join("eval-none");
    let said = ok(&eval(&["--scaling", "none"], &none));
    assert!(said.contains("rescaled by none"), "{said}");
    let err = fails(&eval(&["--scaling", "sideways"], &none));
    assert!(err.contains("sideways") && err.contains("per_trajectory"), "{err}");
    let mean = &report["mean"];
    assert_eq!(mean["truth"]["apd_visible"].as_f64(), Some(1.0), "{mean}");
    for method in ["tracker", "static_baseline"] {
        for k in ["apd_all", "apd_visible", "average_jaccard", "occlusion_accuracy"] {
            let v = mean[method][k].as_f64().unwrap();
            assert!((0.0..=1.0).contains(&v), "{method} {k} {v}");
        }
    }
    assert!(ev.join("scene_00000.png").is_file());

    let (scene, out) = (data.join("scene_00000"), work.join("track"));
    let track = |extra: &[&str]| {
        let args =
            ["track", "--video", arg(&scene), "--autoencoder", arg(&ckpt), "--checkpoint", arg(&tracker)];
        velox(&[&args[..], &["--out", arg(&out)], extra].concat())
    };
    let said = ok(&track(&["--grid", "8"]));
    assert!(said.contains("queries"), "{said}");
    let tracks: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("tracks.json")).unwrap()).unwrap();
    let queries = tracks["queries"].as_array().unwrap();
    assert!(!queries.is_empty());
    assert_eq!(queries[0]["positions"].as_array().unwrap().len(), 24);
    let (_, vertices, _) = ply_vertices(&out.join("tracks_f23.ply"));
    assert_eq!(vertices, queries.len());
    assert!(out.join("overlay/f00.png").is_file() && out.join("overlay/f23.png").is_file());
    assert_eq!(velox_io::image::read_gif(&out.join("overlay.gif")).unwrap().frames.len(), 24);
    // The viewer takes the output: its points frame by frame, and the tracks over them.
    let page = out.join("view.html");
    let said = ok(&velox(&["view", arg(&out), "--html", arg(&page)]));
    assert!(said.contains("24 frame(s)"), "{said}");
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(html.contains("id=\"tracks\"") && html.contains("\"kind\":\"points\""));
    // The scene's video as two video files ffmpeg makes (colour, and millimetres of depth as
    // 16-bit grey), imported and tracked as a user's own clip would be.
    let clip = work.join("clip");
    std::fs::create_dir_all(clip.join("depth")).unwrap();
    for f in 0..24 {
        let (z, w, h) =
            velox_io::image::read_exr_depth(&scene.join(format!("video/f{f:02}_depth.exr"))).unwrap();
        let mm: Vec<u16> = z.iter().map(|&d| (d as f64 * 1000.0).round() as u16).collect();
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, mm)
            .unwrap()
            .save(clip.join(format!("depth/{f:02}.png")))
            .unwrap();
    }
    let ffmpeg = |args: &[&str]| {
        let out = std::process::Command::new("ffmpeg")
            .args(["-v", "error", "-nostdin", "-y", "-framerate", "24"])
            .args(args)
            .output()
            .expect("ffmpeg (tools/setup.sh --tests installs it)");
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    };
    let (colour, depth) = (clip.join("colour.mp4"), clip.join("depth.mkv"));
    ffmpeg(&["-i", arg(&scene.join("video/f%02d.png")), "-pix_fmt", "yuv420p", arg(&colour)]);
    ffmpeg(&["-i", arg(&clip.join("depth/%02d.png")), "-c:v", "ffv1", "-pix_fmt", "gray16le", arg(&depth)]);
    let cam = velox_data::format::read_cameras(&scene).unwrap().video.unwrap();
    let k = serde_json::json!({"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width, "height": cam.height});
    let intrinsics = clip.join("k.json");
    std::fs::write(&intrinsics, k.to_string()).unwrap();
    let imported = work.join("imported");
    let args = ["import", "video", arg(&colour), "--depth", arg(&depth), "--intrinsics", arg(&intrinsics)];
    let said = ok(&velox(&[&args[..], &["--out", arg(&imported)]].concat()));
    assert!(said.contains("24 frames") && said.contains("track the whole clip with"), "{said}");
    let tracked = work.join("tracked");
    let args =
        ["track", "--video", arg(&imported), "--autoencoder", arg(&ckpt), "--checkpoint", arg(&tracker)];
    ok(&velox(&[&args[..], &["--out", arg(&tracked), "--grid", "8"]].concat()));
    let report = velox_io::tracks::TrackReport::read(&tracked).unwrap();
    assert_eq!((report.frames, report.source_frames.len()), (24, 24));
    assert!(!report.queries.is_empty());
    // The same import is a 4D cloud for the autoencoder: encoded and decoded to Gaussians.
    let decoded = work.join("decoded-video");
    let args = ["decode", "gaussians", "--checkpoint", arg(&ckpt), "--cloud", arg(&imported)];
    ok(&velox(&[&args[..], &["--out", arg(&decoded), "--frames", "0,23"]].concat()));
    for f in [0, 23] {
        assert!(ply_vertices(&decoded.join(format!("gaussians_f{f:02}.ply"))).1 > 0);
    }
    // A query outside the scene's box is named.
    let file = work.join("queries.json");
    std::fs::write(&file, "[[0.1, 0.2, 0.3], [0.0, 2.5, 0.0]]").unwrap();
    let err = fails(&track(&["--queries", arg(&file)]));
    assert!(err.contains("query 1"), "{err}");
    // Another autoencoder's tokens would mean something else to the tracker.
    let other = work.join("other.safetensors");
    let mut bytes = std::fs::read(&ckpt).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&other, &bytes).unwrap();
    let args = ["track", "--video", arg(&scene), "--autoencoder", arg(&other), "--checkpoint", arg(&tracker)];
    let err = fails(&velox(&[&args[..], &["--out", arg(&out)]].concat()));
    assert!(err.contains("hash"), "{err}");
    // Nor does it train on them: fine-tuning it on that autoencoder's tokens is refused.
    let other_tokens = work.join("tokens-other");
    let args = ["encode", "--checkpoint", arg(&other), "--data", arg(&data), "--source", "video"];
    ok(&velox(&[&args[..], &["--out", arg(&other_tokens)]].concat()));
    let args =
        ["train", "tracker", "--data", arg(&data), "--tokens", arg(&other_tokens), "--init", arg(&tracker)];
    let err = fails(&velox(&[&args[..], &["--out", arg(&work.join("run2")), "--steps", "1"]].concat()));
    assert!(err.contains("the tracker trained on tokens of autoencoder checkpoint"), "{err}");
}

#[test]
fn generator_trains_generates_and_evaluates() {
    // The generator's commands end to end on the fixture: a few steps of training on the
    // scene's tokens and video, `velox generate` from the scene (Gaussians, renders, sheet),
    // `velox eval generation` beside the encoder's tokens, the image task from one PNG; a
    // DINOv2 file it did not train with, an image for a video generator and another
    // autoencoder are refused.
    let dir = fixture();
    let work = dir.join("generator");
    let data = work.join("data");
    copy_dir(&dir.join("data"), &data);
    let ckpt = dir.join("ae.safetensors");
    ok(&velox(&["encode", "--checkpoint", arg(&ckpt), "--data", arg(&data)]));
    let run = work.join("run");
    let args = ["train", "generator", "--data", arg(&data), "--config", "tiny", "--steps", "2"];
    let said = ok(&velox(&[&args[..], &["--out", arg(&run)]].concat()));
    assert!(said.contains("trained 2 steps"), "{said}");
    let generator = run.join("checkpoint.safetensors");
    let counted = printed_parts(&["config", arg(&generator), "--params"], &["total"])[0];
    let gpu = Gpu::new().unwrap();
    let g = velox_models::velox::generator::Generator::load(&gpu, &generator).unwrap();
    assert_eq!(counted, g.store.num_parameters());
    // The named config took the tokens' count and width, and their statistics.
    let ae_cfg = Autoencoder::checkpoint_config(&ckpt).unwrap();
    assert_eq!((g.cfg.tokens, g.cfg.token_dim), (ae_cfg.encoder.tokens, ae_cfg.encoder.token_dim));
    assert_eq!(g.cfg.token_std.len(), g.cfg.token_dim);

    let scene = data.join("scene_00000");
    let out = work.join("gen");
    let generate = |extra: &[&str]| {
        let args = ["generate", "--checkpoint", arg(&generator), "--autoencoder", arg(&ckpt)];
        velox(
            &[&args[..], &["--out", arg(&out), "--steps", "2", "--frames", "0,23", "--views", "2"], extra]
                .concat(),
        )
    };
    let said = ok(&generate(&["--video", arg(&scene), "--voxels", "input"]));
    assert!(said.contains("generated in"), "{said}");
    for f in
        ["tokens.safetensors", "gaussians_f00.ply", "gaussians_f23.ply", "input/f23.png", "novel/v2_f00.png"]
    {
        assert!(out.join(f).is_file(), "{f}");
    }
    let (sw, sh) = image::image_dimensions(out.join("sheet.png")).unwrap();
    // Rows: the video, the input view and 2 novel views; columns: frames 0 and 23.
    assert_eq!(sh * 2, sw * 4, "{sw} x {sh}");
    // The clip: frames 0 and 23, each the video's frame, the input view and a novel view.
    let clip = velox_io::image::read_gif(&out.join("clip.gif")).unwrap();
    assert_eq!((clip.frames.len(), clip.width), (2, 3 * clip.height));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("generate.json")).unwrap()).unwrap();
    assert_eq!(report["frames"].as_array().unwrap().len(), 2);
    let err = fails(&generate(&["--video", arg(&scene), "--dinov2", arg(&ckpt)]));
    assert!(err.contains("without DINOv2"), "{err}");
    let png = scene.join("video/f00.png");
    let err = fails(&generate(&["--image", arg(&png)]));
    assert!(err.contains("reads videos"), "{err}");

    let ev = work.join("eval");
    let args = ["eval", "generation", "--data", arg(&data), "--checkpoint", arg(&generator)];
    let more = [
        "--autoencoder",
        arg(&ckpt),
        "--voxels",
        "input",
        "--steps",
        "2",
        "--frame-step",
        "12",
        "--views",
        "2",
    ];
    let said = ok(&velox(&[&args[..], &more[..], &["--out", arg(&ev)]].concat()));
    assert!(said.contains("mean generated") && said.contains("mean encoded"), "{said}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(ev.join("generation.json")).unwrap()).unwrap();
    for set in ["generated", "encoded"] {
        for view in ["input", "novel"] {
            let s = &report["mean"][set][view];
            assert!(
                s["psnr"].as_f64().unwrap() > 5.0 && s["ssim"].as_f64().unwrap() <= 1.0,
                "{set} {view}: {s}"
            );
        }
    }
    assert!(ev.join("scene_00000.png").is_file());

    // With DINOv2 (the test fixture's small random model, 64 wide): its features join the
    // condition, and generating without the same weights is refused.
    let dino = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/dinov2/weights.safetensors");
    let run_dino = work.join("run-dino");
    let args = ["train", "generator", "--data", arg(&data), "--config", "tiny", "--steps", "1"];
    ok(&velox(&[&args[..], &["--out", arg(&run_dino), "--dinov2", arg(&dino)]].concat()));
    let dino_gen = run_dino.join("checkpoint.safetensors");
    let g = velox_models::velox::generator::Generator::load(&gpu, &dino_gen).unwrap();
    assert_eq!(g.cfg.dino_width, 64);
    let args =
        ["generate", "--checkpoint", arg(&dino_gen), "--autoencoder", arg(&ckpt), "--video", arg(&scene)];
    let out_dino = work.join("gen-dino");
    let more =
        ["--out", arg(&out_dino), "--steps", "1", "--frames", "0", "--views", "1", "--voxels", "input"];
    let err = fails(&velox(&[&args[..], &more[..]].concat()));
    assert!(err.contains("--dinov2"), "{err}");
    ok(&velox(&[&args[..], &more[..], &["--dinov2", arg(&dino)]].concat()));
    assert!(out_dino.join("sheet.png").is_file());

    // The image task: trained on each scene's first frame, generating from one PNG.
    let run_image = work.join("run-image");
    let args =
        ["train", "generator", "--data", arg(&data), "--config", "tiny", "--steps", "1", "--task", "image"];
    ok(&velox(&[&args[..], &["--out", arg(&run_image)]].concat()));
    let image_gen = run_image.join("checkpoint.safetensors");
    let args =
        ["generate", "--checkpoint", arg(&image_gen), "--autoencoder", arg(&ckpt), "--image", arg(&png)];
    let out_image = work.join("gen-image");
    let said = ok(&velox(
        &[&args[..], &["--out", arg(&out_image), "--steps", "1", "--frames", "0", "--views", "1"]].concat(),
    ));
    assert!(said.contains("generated in") && out_image.join("input/f00.png").is_file(), "{said}");

    // Another autoencoder's tokens would mean something else to the generator.
    let other = work.join("other.safetensors");
    let mut bytes = std::fs::read(&ckpt).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&other, &bytes).unwrap();
    let args =
        ["generate", "--checkpoint", arg(&generator), "--autoencoder", arg(&other), "--video", arg(&scene)];
    let err = fails(&velox(&[&args[..], &["--out", arg(&out)]].concat()));
    assert!(err.contains("hash"), "{err}");
}

#[test]
fn eval_cloth_reports_the_centre_of_mass_along_gravity_with_plots() {
    // A cloth scene, its tokens from the fixture's autoencoder, an image-to-4D generator
    // trained one step, and `velox eval cloth`: the report and the three plots.
    let dir = fixture();
    let work = dir.join("cloth");
    let data = work.join("data");
    let args = ["data", "cloth", "--scenes", "1", "--res", "16", "--points", "4000", "--tracks", "8"];
    ok(&velox(&[&args[..], &["--out", arg(&data)]].concat()));
    let ckpt = dir.join("ae.safetensors");
    ok(&velox(&["encode", "--checkpoint", arg(&ckpt), "--data", arg(&data)]));
    let run = work.join("run");
    let args =
        ["train", "generator", "--data", arg(&data), "--config", "tiny", "--steps", "1", "--task", "image"];
    ok(&velox(&[&args[..], &["--out", arg(&run)]].concat()));
    let out = work.join("eval");
    let generator = run.join("checkpoint.safetensors");
    let args = ["eval", "cloth", "--data", arg(&data), "--checkpoint", arg(&generator)];
    let more = ["--autoencoder", arg(&ckpt), "--points", "64", "--sample-steps", "2", "--steps", "2"];
    let said = ok(&velox(&[&args[..], &more[..], &["--out", arg(&out)]].concat()));
    assert!(said.contains("RMSE along gravity") && said.contains("mean"), "{said}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("cloth.json")).unwrap()).unwrap();
    let scene = &report["scenes"][0];
    assert_eq!(scene["simulated"].as_array().unwrap().len(), 24);
    for k in ["rmse_generated", "rmse_encoded"] {
        assert!(scene[k].as_f64().unwrap().is_finite(), "{k}: {scene}");
    }
    for plot in ["height", "velocity", "acceleration"] {
        assert!(out.join(format!("cloth_00000_{plot}.png")).is_file(), "{plot}");
    }
    // The clip: the scene beside the generated and the encoded surface, every frame.
    let clip = velox_io::image::read_gif(&out.join("cloth_00000.gif")).unwrap();
    assert_eq!((clip.frames.len(), clip.width), (24, 3 * clip.height));
    // A scene without cloth.json is not a cloth scene.
    std::fs::remove_file(data.join("cloth_00000/cloth.json")).unwrap();
    let err = fails(&velox(&[&args[..], &more[..], &["--out", arg(&out)]].concat()));
    assert!(err.contains("cloth.json") && err.contains("velox data cloth"), "{err}");
}
