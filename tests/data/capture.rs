//! RGBD captures imported as the tracker's video (`velox::data::capture`): a procedural scene's
//! video written out as a capture (colour PNGs, 16-bit millimetre depth PNGs, intrinsics of an
//! image twice the size) comes back as a video whose points are the capture's, fitted into the
//! box, with the frames it took; bad captures are refused naming the problem.

use std::path::Path;

use crate::common::*;
use crate::data::temp_dir;
use velox::data::capture::{import_rgbd, CaptureOptions, FILL};
use velox::data::format::write_scene;
use velox::data::procedural::{scene, FRAMES};
use velox::data::rgbd::{read_scene_video, read_video_folder, rgbd_cloud, RgbdVideo};
use velox::data::SynthOptions;

/// Writes `video`'s frames `order` as a capture in `dir` (depth in millimetres).
fn write_capture(dir: &Path, video: &RgbdVideo, order: &[usize]) {
    let cam = &video.camera;
    let (w, h) = (cam.width, cam.height);
    std::fs::create_dir_all(dir.join("rgb")).unwrap();
    std::fs::create_dir_all(dir.join("depth")).unwrap();
    for (k, &f) in order.iter().enumerate() {
        velox::io::image::write_png(&dir.join(format!("rgb/{k:06}.png")), &video.rgb[f], w, h).unwrap();
        let mm: Vec<u16> = video.depth[f].iter().map(|&z| (z as f64 * 1000.0).round() as u16).collect();
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, mm)
            .unwrap()
            .save(dir.join(format!("depth/{k:06}.png")))
            .unwrap();
    }
    // Intrinsics of an image twice the depth's size: the import scales them to the depth's.
    let k = serde_json::json!({
        "fx": 2.0 * cam.fx, "fy": 2.0 * cam.fy, "cx": 2.0 * cam.cx, "cy": 2.0 * cam.cy,
        "width": 2 * w, "height": 2 * h,
    });
    std::fs::write(dir.join("intrinsics.json"), k.to_string()).unwrap();
}

/// A procedural scene of `seed` (24 px, as the tests here need) written under `root/scene`, and
/// its RGBD video.
fn scene_video(root: &Path, seed: u64) -> RgbdVideo {
    let (_, mesh) = scene(seed, None).unwrap();
    let opts = SynthOptions { res: 24, points: 500, supersample: 1, tracks: 6, ..Default::default() };
    let name = format!("procedural seed {seed}");
    write_scene(&gpu(), &mesh, &name, None, seed, &opts, &root.join("scene"), &mut |_| {}).unwrap();
    read_scene_video(&root.join("scene")).unwrap()
}

/// The camera-frame points (metres) of a frame's depth under `video`'s intrinsics.
fn camera_points(video: &RgbdVideo, f: usize) -> Vec<[f64; 3]> {
    let c = &video.camera;
    video.depth[f]
        .iter()
        .enumerate()
        .filter(|(_, z)| **z > 0.0)
        .map(|(i, &z)| {
            let (u, v) = ((i as u32 % c.width) as f64 + 0.5, (i as u32 / c.width) as f64 + 0.5);
            let z = (z as f64 * 1000.0).round() / 1000.0;
            [(u - c.cx as f64) / c.fx as f64 * z, (v - c.cy as f64) / c.fy as f64 * z, z]
        })
        .collect()
}

#[test]
fn a_capture_becomes_the_trackers_video_in_the_box() {
    let root = temp_dir("capture");
    let source = scene_video(&root, 4);
    write_capture(&root.join("capture"), &source, &(0..FRAMES).collect::<Vec<_>>());

    let record = import_rgbd(&root.join("capture"), &root.join("video"), &CaptureOptions::default()).unwrap();
    let window = &record.windows[0];
    assert_eq!((record.windows.len(), window.dir.as_str()), (1, "."));
    assert_eq!(window.frames, (0..FRAMES).collect::<Vec<_>>());
    assert_eq!((window.colour_files[3].as_str(), &window.times), ("000003.png", &None));
    let video = read_video_folder(&root.join("video")).unwrap();
    let cam = &video.camera;
    assert_eq!((cam.width, cam.height, cam.fx), (24, 24, source.camera.fx), "intrinsics at the depth's size");
    assert_eq!(video.rgb[5], source.rgb[5], "the colour, unresized");
    // Every pixel's point, taken back to metres, is the capture's.
    for f in [0, 11, 23] {
        let want = camera_points(&source, f);
        let got: Vec<[f64; 3]> = video.depth[f]
            .iter()
            .enumerate()
            .filter(|(_, z)| **z > 0.0)
            .map(|(i, &z)| {
                let p = cam.unproject((i as u32 % 24) as f32 + 0.5, (i as u32 / 24) as f32 + 0.5, z);
                std::array::from_fn(|a| record.centre[a] + p[a] as f64 / record.scale)
            })
            .collect();
        assert_eq!(got.len(), want.len(), "frame {f}");
        let worst = got
            .iter()
            .zip(&want)
            .flat_map(|(g, w)| (0..3).map(move |a| (g[a] - w[a]).abs()))
            .fold(0.0, f64::max);
        assert!(worst < 1e-5, "frame {f}: {worst}");
    }
    // The points fill the box to FILL along their longest side, and no further.
    let cloud = rgbd_cloud(&video, usize::MAX, 0).unwrap();
    let extent = (0..3)
        .map(|a| {
            let (lo, hi) = cloud.iter().fold((f32::MAX, f32::MIN), |(l, h), p| (l.min(p[a]), h.max(p[a])));
            assert!(lo >= -FILL - 1e-4 && hi <= FILL + 1e-4, "axis {a}: {lo} to {hi}");
            hi - lo
        })
        .fold(0.0f32, f32::max);
    assert!((extent - 2.0 * FILL).abs() < 0.05, "the longest side spans {extent}");

    // A longer clip is resampled to 24 frames spread over it, the first and the last kept.
    let long: Vec<usize> = (0..30).map(|k| k * (FRAMES - 1) / 29).collect();
    write_capture(&root.join("long"), &source, &long);
    let record =
        import_rgbd(&root.join("long"), &root.join("long-video"), &CaptureOptions::default()).unwrap();
    let frames = &record.windows[0].frames;
    assert_eq!((record.source_frames, frames[0], frames[23]), (30, 0, 29));
    assert!(frames.windows(2).all(|w| w[1] > w[0]));

    // Or cut into windows of consecutive frames, fitted into the box together, with times.
    let windows = CaptureOptions { windows: Some(4), fps: Some(30.0), ..Default::default() };
    let longer: Vec<usize> = (0..40).map(|k| k * (FRAMES - 1) / 39).collect();
    write_capture(&root.join("longer"), &source, &longer);
    let record = import_rgbd(&root.join("longer"), &root.join("windows"), &windows).unwrap();
    let dirs: Vec<&str> = record.windows.iter().map(|w| w.dir.as_str()).collect();
    assert_eq!(dirs, ["window_000", "window_001"]);
    assert_eq!(
        record.windows[1].frames,
        (16..40).collect::<Vec<_>>(),
        "the last window ends on the last frame"
    );
    assert_eq!(record.windows[1].times.as_ref().unwrap()[0], 16.0 / 30.0);
    let (a, b) = (
        read_video_folder(&root.join("windows/window_000")).unwrap(),
        read_video_folder(&root.join("windows/window_001")).unwrap(),
    );
    assert_eq!(a.camera, b.camera, "one fit for every window");
    assert_eq!(a.depth[16..], b.depth[..8], "the overlap is the same frames");
    assert_eq!(velox::data::capture::window_starts(24, 4), vec![0]);
    assert_eq!(velox::data::capture::window_starts(60, 4), vec![0, 20, 36]);
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn bad_captures_are_refused_naming_the_problem() {
    let root = temp_dir("capture-bad");
    let (_, mesh) = scene(5, None).unwrap();
    let opts = SynthOptions { res: 16, points: 300, supersample: 1, tracks: 4, ..Default::default() };
    write_scene(&gpu(), &mesh, "procedural seed 5", None, 5, &opts, &root.join("scene"), &mut |_| {})
        .unwrap();
    let source = read_scene_video(&root.join("scene")).unwrap();
    let err = |dir: &Path, options: &CaptureOptions| {
        import_rgbd(dir, &root.join("out"), options).expect_err("refused").to_string()
    };
    let short = root.join("short");
    write_capture(&short, &source, &(0..10).collect::<Vec<_>>());
    assert!(err(&short, &CaptureOptions::default()).contains("10 frames: the video takes 24"));
    let full = root.join("full");
    write_capture(&full, &source, &(0..FRAMES).collect::<Vec<_>>());
    let near = CaptureOptions { max_depth: Some(1e-3), ..Default::default() };
    assert!(err(&full, &near).contains("no pixel of the frames taken has a depth"));
    let e = err(&full, &CaptureOptions { windows: Some(24), ..Default::default() });
    assert!(e.contains("the overlap must be below 24"), "{e}");
    let e = err(&full, &CaptureOptions { depth_scale: -1.0, ..Default::default() });
    assert!(e.contains("depth scale -1 must be positive"), "{e}");
    std::fs::remove_file(full.join("depth/000023.png")).unwrap();
    assert!(err(&full, &CaptureOptions::default()).contains("24 colour frames and 23 depth frames"));
    image::GrayImage::new(16, 16).save(full.join("depth/000023.png")).unwrap();
    let e = err(&full, &CaptureOptions::default());
    assert!(e.contains("000023.png") && e.contains("16-bit greyscale"), "{e}");
    std::fs::remove_file(full.join("intrinsics.json")).unwrap();
    assert!(err(&full, &CaptureOptions::default()).contains("intrinsics.json"));
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn windows_are_tracked_as_one_clip_each_from_where_the_last_left_off() {
    use velox::models::config::{AutoencoderConfig, TrackerConfig};
    use velox::models::velox::autoencoder::Autoencoder;
    use velox::models::velox::tracker::Tracker;
    use velox::tasks::track::{grid_queries, read_windows, track, track_windows};

    let root = temp_dir("capture-windows");
    let source = scene_video(&root, 6);
    let order: Vec<usize> = (0..40).map(|k| k * (FRAMES - 1) / 39).collect();
    write_capture(&root.join("capture"), &source, &order);
    let options = CaptureOptions { windows: Some(4), ..Default::default() };
    import_rgbd(&root.join("capture"), &root.join("video"), &options).unwrap();
    let windows = read_windows(&root.join("video")).unwrap().expect("an import in windows");
    assert_eq!(windows.len(), 2);

    let gpu = gpu();
    let ae = Autoencoder::new(&gpu, &AutoencoderConfig::tiny(), 1).unwrap();
    let tracker = Tracker::new(&gpu, &TrackerConfig { token_dim: 8, ..TrackerConfig::tiny() }, 2).unwrap();
    let queries = grid_queries(&windows[0].0, 6);
    assert!(!queries.is_empty());
    let stitched = track_windows(&ae, &tracker, &windows, &queries, 2000, 3).unwrap();
    assert_eq!(stitched.frames, (0..40).collect::<Vec<_>>());
    assert!(stitched.tracks.iter().all(|t| t.len() == 40) && stitched.visible.iter().all(|v| v.len() == 40));
    // The first window as one clip; the second from where the first puts the queries on frame
    // 16, taking over after frame 23.
    let a = track(&ae, &tracker, &windows[0].0, &queries, 2000, 3).unwrap();
    let from: Vec<[f32; 3]> = a.tracks.iter().map(|t| t[16]).collect();
    let b = track(&ae, &tracker, &windows[1].0, &from, 2000, 3).unwrap();
    for q in 0..queries.len() {
        assert_eq!(stitched.tracks[q][..24], a.tracks[q][..]);
        assert_eq!(stitched.tracks[q][24..], b.tracks[q][8..]);
        assert_eq!(stitched.visible[q][24..], b.visible[q][8..]);
    }
    // A window that does not start inside the one before is refused.
    let gap = [windows[0].clone(), (windows[1].0.clone(), (30..54).collect())];
    let e = track_windows(&ae, &tracker, &gap, &queries, 2000, 3).err().unwrap().to_string();
    assert!(e.contains("does not start inside the one before"), "{e}");
    assert!(read_windows(&root.join("scene")).unwrap().is_none());
    let _ = std::fs::remove_dir_all(&root);
}

/// Runs ffmpeg (tools/setup.sh --tests installs it) with `args`.
fn ffmpeg(args: &[&str], dir: &Path) {
    let out = std::process::Command::new("ffmpeg")
        .args(["-v", "error", "-nostdin", "-y"])
        .args(args)
        .current_dir(dir)
        .output()
        .expect("ffmpeg (tools/setup.sh --tests installs it)");
    assert!(out.status.success(), "ffmpeg {args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn a_video_with_its_depth_video_imports_as_its_frames_do() {
    use velox::data::video::{frame_rate, import_video, VideoOptions};
    let root = temp_dir("capture-video");
    let source = scene_video(&root, 5);
    // 30 frames as a capture, then as two lossless videos ffmpeg makes of them at 15 fps:
    // colour as FFV1 RGB, depth as FFV1 16-bit grey (millimetres).
    let order: Vec<usize> = (0..30).map(|k| k * (FRAMES - 1) / 29).collect();
    let capture = root.join("capture");
    write_capture(&capture, &source, &order);
    ffmpeg(
        &["-framerate", "15", "-i", "rgb/%06d.png", "-c:v", "ffv1", "-pix_fmt", "bgr0", "colour.mkv"],
        &capture,
    );
    ffmpeg(
        &["-framerate", "15", "-i", "depth/%06d.png", "-c:v", "ffv1", "-pix_fmt", "gray16le", "depth.mkv"],
        &capture,
    );
    assert_eq!(frame_rate(&capture.join("colour.mkv")).unwrap(), Some(15.0));

    let with_depth = VideoOptions {
        depth: Some(capture.join("depth.mkv")),
        intrinsics: Some(capture.join("intrinsics.json")),
        ..Default::default()
    };
    let imported = import_video(&capture.join("colour.mkv"), &root.join("video"), &with_depth).unwrap();
    assert_eq!((imported.frames, imported.width, imported.height, imported.fps), (30, 24, 24, Some(15.0)));
    let record = imported.capture.unwrap();
    assert_eq!(record.fps, Some(15.0));
    assert_eq!(record.windows[0].times.as_ref().unwrap()[23], 29.0 / 15.0, "the last frame's time");
    // The same video as the capture's frames make, to the bit (the codecs are lossless).
    let direct = import_rgbd(&capture, &root.join("direct"), &CaptureOptions::default()).unwrap();
    assert_eq!(
        (record.centre, record.scale, &record.windows[0].frames),
        (direct.centre, direct.scale, &direct.windows[0].frames)
    );
    let (a, b) =
        (read_video_folder(&root.join("video")).unwrap(), read_video_folder(&root.join("direct")).unwrap());
    assert_eq!((a.camera, &a.rgb, &a.depth), (b.camera, &b.rgb, &b.depth));

    // Colour alone: its frames, at the rate asked for, for the generator's condition.
    let frames = root.join("frames");
    let only = VideoOptions { fps: Some(5.0), ..Default::default() };
    let imported = import_video(&capture.join("colour.mkv"), &frames, &only).unwrap();
    assert_eq!((imported.frames, imported.fps, imported.capture.is_none()), (10, Some(5.0), true));
    let (rgb, w, h) = velox::io::image::read_png(&frames.join("frame_00001.png")).unwrap();
    assert_eq!((w, h), (24, 24));
    let near = (2..=4).find(|&k| rgb == source.rgb[order[k]]);
    assert!(near.is_some(), "frame 1 at 5 fps is one of the source's frames 2 to 4 at 15");

    // What cannot be imported is refused, naming why.
    let e = |o: &VideoOptions, out: &str| {
        import_video(&capture.join("colour.mkv"), &root.join(out), o).unwrap_err().to_string()
    };
    assert!(e(&only, "frames").contains("not empty"));
    let no_k = VideoOptions { depth: Some(capture.join("depth.mkv")), ..Default::default() };
    assert!(e(&no_k, "a").contains("needs the camera's intrinsics"));
    let short = root.join("short.mkv");
    ffmpeg(&["-i", "depth.mkv", "-frames:v", "20", "-c:v", "ffv1", short.to_str().unwrap()], &capture);
    let mismatched = VideoOptions { depth: Some(short), ..with_depth.clone() };
    let err = e(&mismatched, "b");
    assert!(err.contains("30 frames") && err.contains("has 20"), "{err}");
    std::fs::write(root.join("not-a-video.mkv"), b"text").unwrap();
    let err = import_video(&root.join("not-a-video.mkv"), &root.join("c"), &only).unwrap_err().to_string();
    assert!(err.contains("ffmpeg failed"), "{err}");
    let _ = std::fs::remove_dir_all(&root);
}
