//! The `velox` command as a user meets it: its reports, its benchmark JSON, and its errors.

use std::process::Command;

mod common;

fn velox() -> Command {
    Command::new(env!("CARGO_BIN_EXE_velox"))
}

#[test]
fn info_reports_device_features_and_variants() {
    let out = velox().arg("info").output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}\n{}", String::from_utf8_lossy(&out.stderr));
    for needle in
        ["Chosen device", "subgroup size", "shared memory", "coop matrices", "matmul f16", "scatter-add"]
    {
        assert!(text.contains(needle), "missing {needle:?} in:\n{text}");
    }
}

#[test]
fn missing_driver_names_the_packages_to_install() {
    let out = velox()
        .arg("info")
        .env("VK_DRIVER_FILES", "/nonexistent/icd.json")
        .env("VK_ICD_FILENAMES", "/nonexistent/icd.json")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("libvulkan1 mesa-vulkan-drivers"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn missing_ffmpeg_names_the_package_to_install() {
    let dir = std::env::temp_dir().join(format!("velox-no-ffmpeg-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("clip.mp4"), b"not decoded").unwrap();
    let out = velox()
        .args(["import", "video"])
        .arg(dir.join("clip.mp4"))
        .arg("--out")
        .arg(dir.join("frames"))
        .env("PATH", "")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("is not on PATH") && err.contains("apt-get install ffmpeg"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn config_prints_json_that_reads_back() {
    let out = velox().args(["config", "tiny"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let mut cfg: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(cfg["name"], "tiny");
    assert_eq!(cfg["views_per_step"], 1);
    // An edited copy is a config file.
    cfg["views_per_step"] = 3.into();
    let path = std::env::temp_dir().join(format!("velox-config-{}.json", std::process::id()));
    std::fs::write(&path, cfg.to_string()).unwrap();
    let out = velox().args(["config", path.to_str().unwrap()]).output().unwrap();
    let back: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(back["views_per_step"], 3);
    std::fs::remove_file(&path).ok();
    let out = velox().args(["config", "no-such-config"]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("paper, small or tiny"));
}

#[test]
fn unknown_device_choice_is_a_clear_error() {
    let out = velox().arg("info").env("VELOX_DEVICE", "no-such-device").output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("VELOX_DEVICE \"no-such-device\" matches none"), "{err}");
}

#[test]
fn bench_kernels_writes_records_with_time_and_error() {
    let dir = std::env::temp_dir().join(format!("velox-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("bench.json");
    let out = velox()
        .args(["bench", "kernels", "--quick", "--repeats", "1", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let records: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let records = records.as_array().unwrap();
    for name in ["matmul", "softmax", "exclusive scan", "radix sort pairs", "scatter-add"] {
        assert!(records.iter().any(|r| r["name"].as_str().unwrap().starts_with(name)), "no {name} record");
    }
    for r in records {
        for field in
            ["name", "shape", "precision", "device", "median_ms", "throughput", "nmse", "max_abs_err"]
        {
            assert!(!r[field].is_null(), "record without {field}: {r}");
        }
        assert!(r["median_ms"].as_f64().unwrap() > 0.0);
        // Every kernel in the quick set is accurate: f32 paths to 1e-9, f16 inputs to 1e-6
        // (against the product of the rounded inputs), the integer kernels exactly.
        let bound = if r["precision"] == "f16->f32" { 1e-6 } else { 1e-9 };
        assert!(r["nmse"].as_f64().unwrap() <= bound, "{r}");
        // Every record says its work: FLOPs (none for the integer kernels) and bytes.
        assert!(r["flops"].as_f64().unwrap() >= 0.0 && r["bytes"].as_f64().unwrap() > 0.0, "{r}");
    }
    // An n^3 f32 product: 2 n^3 FLOPs over three n x n matrices of 4 bytes, n / 6 FLOPs a byte.
    let r = records.iter().find(|r| r["shape"] == "128x128x128" && r["precision"] == "f32").unwrap();
    let intensity = r["flops"].as_f64().unwrap() / r["bytes"].as_f64().unwrap();
    assert!((intensity - 128.0 / 6.0).abs() < 1e-9, "{r}");
    assert!(r["kernel"].as_str().is_some_and(|k| !k.is_empty()), "{r}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_arguments_are_refused_with_usage() {
    let out = velox().args(["bench", "kernels", "--repeats", "0"]).output().unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("repeats"));
}

#[test]
fn bench_attention_reports_every_variant_with_small_error() {
    let dir = std::env::temp_dir().join(format!("velox-bench-attn-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("attn.json");
    let out = velox()
        .args(["bench", "attention", "--quick", "--repeats", "1", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let records: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let records = records.as_array().unwrap();
    for case in ["dense self", "window self", "cell cross", "global cross"] {
        for pass in ["fwd", "bwd"] {
            let name = format!("attn {case} {pass}");
            let r =
                records.iter().find(|r| r["name"] == name.as_str()).unwrap_or_else(|| panic!("no {name}"));
            assert!(r["nmse"].as_f64().unwrap() < 1e-10, "{r}");
            // The work and the kernel chosen: a backward does 2.5 times a forward's FLOPs.
            assert!(r["bytes"].as_f64().unwrap() > 0.0 && r["kernel"].is_string(), "{r}");
        }
        let flops = |pass: &str| {
            let name = format!("attn {case} {pass}");
            records.iter().find(|r| r["name"] == name.as_str() && r["precision"] == "f32").unwrap()["flops"]
                .as_f64()
                .unwrap()
        };
        assert!((flops("bwd") / flops("fwd") - 2.5).abs() < 1e-12, "{case}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bench_layers_reports_forward_and_backward_with_small_error() {
    let dir = std::env::temp_dir().join(format!("velox-bench-layers-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("layers.json");
    let out =
        velox().args(["bench", "layers", "--quick", "--repeats", "1", "--json"]).arg(&json).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let records: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let records = records.as_array().unwrap();
    assert_eq!(records.len(), 12, "six layers, forward and forward+backward");
    for r in records {
        // The Fourier embedding's top frequency (2^12 pi) multiplies the f32 rounding of its
        // argument into the phase, which the f64 reference does not have.
        let bound = if r["name"].as_str().unwrap().starts_with("fourier") { 1e-7 } else { 1e-11 };
        assert!(r["nmse"].as_f64().unwrap() < bound, "{r}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn demo_runs_end_to_end_and_says_where_its_outputs_are() {
    let dir = std::env::temp_dir().join(format!("velox-demo-{}", std::process::id()));
    let out = velox()
        .args(["demo", "--steps", "4", "--res", "32", "--points", "2000", "--config", "tiny", "--out"])
        .arg(&dir)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(text.contains("Outputs in"), "{text}");
    for f in [
        "train/loss.png",
        "train/checkpoint.safetensors",
        "decoded/points_f12.ply",
        "decoded/gaussians_f23.ply",
        "eval/eval.json",
        "demo.json",
        "decoded.gif",
    ] {
        assert!(dir.join(f).exists(), "the demo did not write {f}");
    }
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("demo.json")).unwrap()).unwrap();
    assert!(summary["metrics"]["psnr"].as_f64().unwrap().is_finite());
    // The clip, every other frame: the truth beside the decoded Gaussians, two views of 32
    // enlarged 4 times to reach 256 px.
    let gif = velox_io::image::read_gif(&dir.join("decoded.gif")).unwrap();
    assert_eq!((gif.frames.len(), gif.width, gif.height), (12, 256, 128));
    // Every frame decoded as Gaussians (what the viewer plays), and the viewer's command given.
    assert!(dir.join("decoded/gaussians_f00.ply").exists() && dir.join("decoded/gaussians_f11.ply").exists());
    assert!(text.contains(&format!("view {}", dir.join("decoded").display())), "{text}");
    // decode.json names the scene, which the viewer shows beside the frames with its cameras.
    let decode: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("decoded/decode.json")).unwrap()).unwrap();
    assert_eq!(decode["cloud"], dir.join("data/scene_00000").display().to_string());
    assert_eq!(decode["frames"].as_array().unwrap().len(), 24);
    assert!(gif.frames[0] != gif.frames[6], "the clip moves");
    // A second run replaces the first demo's outputs; a folder that is not a demo's is refused.
    let again = velox()
        .args(["demo", "--steps", "1", "--res", "16", "--points", "500", "--config", "tiny", "--out"])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(again.status.success(), "{}", String::from_utf8_lossy(&again.stderr));
    let other = std::env::temp_dir().join(format!("velox-not-a-demo-{}", std::process::id()));
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("precious.txt"), "keep").unwrap();
    let refused = velox().args(["demo", "--out"]).arg(&other).output().unwrap();
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("not a previous demo"));
    assert!(other.join("precious.txt").exists());
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&other).ok();
}

#[cfg(unix)]
#[test]
fn a_write_past_the_file_size_limit_stops_with_the_file_named() {
    // With no room under the file size limit, SIGXFSZ would end the process without a word;
    // velox ignores it, so the write fails with EFBIG and the run stops with a message. (A
    // command that renders cannot run under a small limit on lavapipe: its device memory lives
    // in memfds that the limit also caps, and it dies of SIGBUS at its first large allocation.)
    let dir = std::env::temp_dir().join(format!("velox-ulimit-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("info.json");
    let run = Command::new("sh")
        .args(["-c", "ulimit -f 0 && exec \"$0\" \"$@\"", env!("CARGO_BIN_EXE_velox"), "info", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "an exit with an error, not a signal: {:?}\n{err}", run.status);
    assert!(err.contains(&format!("cannot write {}: File too large", json.display())), "{err}");
    assert!(!json.exists(), "no truncated file at the target name");
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0, "no temporary file left behind");
    std::fs::remove_dir_all(&dir).ok();
}

#[cfg(target_os = "linux")]
#[test]
fn a_render_onto_a_full_disk_stops_with_the_file_named() {
    use velox_engine::ops::raster::GaussianData;
    use velox_io::{ply, temp_path};

    let dir = std::env::temp_dir().join(format!("velox-full-disk-{}", std::process::id()));
    let out = dir.join("frames");
    std::fs::create_dir_all(&out).unwrap();
    let mut g = GaussianData::benchmark_scene(500, 3);
    g.means.iter_mut().skip(2).step_by(3).for_each(|z| *z -= 3.0);
    let scene = dir.join("scene.ply");
    ply::write(&scene, &g).unwrap();
    // The second frame's temporary file leads to /dev/full, which fails every write with
    // ENOSPC as a full disk does.
    let png = out.join("frame_0001.png");
    std::os::unix::fs::symlink("/dev/full", temp_path(&png)).unwrap();
    let run = velox()
        .arg("render")
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .args(["--frames", "3", "--width", "48", "--height", "32", "--no-depth"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{:?}\n{err}", run.status);
    assert!(err.contains(&format!("cannot write {}: No space left on device", png.display())), "{err}");
    assert!(out.join("frame_0000.png").exists(), "the frame before is complete");
    assert!(!png.exists() && !out.join("frame_0002.png").exists(), "the run stopped at the failed frame");
    assert!(!out.join("render.json").exists());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn data_synth_refuses_empty_or_oversized_requests_and_notes_fewer_tracks() {
    let dir = std::env::temp_dir().join(format!("velox-synth-limits-{}", std::process::id()));
    let synth =
        |extra: &[&str]| velox().args(["data", "synth", "--out"]).arg(&dir).args(extra).output().unwrap();
    for (args, needle) in [
        (&["--points", "0"][..], "1..=16777216"),
        (&["--scenes", "0"][..], "1..=1000000"),
        (&["--tracks", "1000000000"][..], "0..=1048576"),
    ] {
        let out = synth(args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} was accepted");
        assert!(err.contains(args[0]) && err.contains(needle), "{args:?}: {err}");
    }
    assert!(!dir.exists(), "a refused request wrote {}", dir.display());
    let help = velox().args(["data", "synth", "--help"]).output().unwrap();
    let help = String::from_utf8_lossy(&help.stdout);
    assert!(help.contains("0 to 1048576") && help.contains("a note says so"), "{help}");
    // More tracks than frame 0 shows surface pixels: one per pixel, and a note.
    let out = synth(&["--scenes", "1", "--res", "8", "--points", "200", "--tracks", "1048576"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("note: scene_00000") && err.contains("tracks of the 1048576 asked for"), "{err}");
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("scene_00000/meta.json")).unwrap()).unwrap();
    let tracks = meta["tracks"].as_u64().unwrap();
    assert!(tracks > 0 && tracks <= 35 * 64, "{tracks} tracks from 35 views of 8 x 8");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn config_files_with_huge_sizes_or_infinite_numbers_are_refused() {
    let out = velox().args(["config", "tiny"]).output().unwrap();
    let tiny: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let path = std::env::temp_dir().join(format!("velox-config-limits-{}.json", std::process::id()));
    for (section, field, value, needle) in [
        ("encoder", "tokens", "1000000000000000000", "encoder.tokens is 1000000000000000000"),
        ("encoder", "time_scale", "1e39", "encoder.time_scale is inf"),
        ("gaussians", "window_voxels", "0", "gaussians.window_voxels is 0"),
    ] {
        let mut cfg = tiny.clone();
        cfg[section][field] = serde_json::from_str(value).unwrap();
        std::fs::write(&path, cfg.to_string()).unwrap();
        let out = velox().arg("config").arg(&path).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{section}.{field} = {value} was accepted");
        assert!(err.contains(path.to_str().unwrap()) && err.contains(needle), "{err}");
    }
    std::fs::remove_file(&path).ok();
}

#[test]
fn data_cloth_writes_scenes_with_their_centre_of_mass_and_refuses_bad_requests() {
    let dir = std::env::temp_dir().join(format!("velox-cloth-{}", std::process::id()));
    let cloth =
        |extra: &[&str]| velox().args(["data", "cloth", "--out"]).arg(&dir).args(extra).output().unwrap();
    for (args, needle) in
        [(&["--scenes", "0"][..], "1..=1000000"), (&["--split", "dev"][..], "train, val, test")]
    {
        let out = cloth(args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} was accepted");
        assert!(err.contains(needle), "{args:?}: {err}");
    }
    assert!(!dir.exists(), "a refused request wrote {}", dir.display());
    let out =
        cloth(&["--scenes", "1", "--res", "16", "--points", "2000", "--tracks", "8", "--split", "test"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let scene = dir.join("cloth_00000");
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("meta.json")).unwrap()).unwrap();
    assert!(meta["source"].as_str().unwrap().contains("cloth seed 2199023255552"), "{meta}");
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("cloth.json")).unwrap()).unwrap();
    let com = record["centre_of_mass"].as_array().unwrap();
    assert_eq!(com.len(), 24);
    let up: Vec<f64> = record["up"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    let height = |f: usize| (0..3).map(|k| com[f][k].as_f64().unwrap() * up[k]).sum::<f64>();
    assert!(height(23) < height(0) - 0.05, "the cloth did not fall: {} -> {}", height(0), height(23));
    std::fs::remove_dir_all(&dir).ok();
}

/// Every file under `dir` (relative path, bytes), in name order.
fn tree(dir: &std::path::Path) -> Vec<(String, Vec<u8>)> {
    common::files_under(dir).into_iter().map(|(name, p)| (name, std::fs::read(p).unwrap())).collect()
}

#[test]
fn gltf_batches_import_folders_and_lists_report_failures_and_resume() {
    let dir = std::env::temp_dir().join(format!("velox-batch-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let input = dir.join("in");
    std::fs::create_dir_all(input.join("sub")).unwrap();
    std::fs::create_dir_all(input.join("bad")).unwrap();
    let fixtures = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/gltf");
    std::fs::copy(fixtures.join("SimpleSkin.gltf"), input.join("a.gltf")).unwrap();
    std::fs::copy(fixtures.join("SimpleSkin.gltf"), input.join("sub/b.GLTF")).unwrap();
    std::fs::copy(fixtures.join("MorphStressTest.gltf"), input.join("sub/c.gltf")).unwrap();
    std::fs::write(input.join("bad/broken.glb"), b"glTF not really").unwrap();
    std::fs::write(input.join("notes.txt"), b"not a glTF file").unwrap();
    let small = ["--res", "8", "--points", "200", "--tracks", "0"];
    let run = |args: &[&str], out: &str| {
        velox()
            .args(["data", "gltf"])
            .args(args)
            .arg("--out")
            .arg(dir.join(out))
            .args(small)
            .output()
            .unwrap()
    };
    let report = |out: &str| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(dir.join(out).join("report.json")).unwrap()).unwrap()
    };
    let input_arg = input.to_str().unwrap();

    // A folder, searched at any depth in name order: the broken file is reported, the others
    // are written, and the command says it failed.
    let first = run(&[input_arg, "--jobs", "2"], "o1");
    let err = String::from_utf8_lossy(&first.stderr);
    assert!(!first.status.success(), "a failed file must fail the command");
    assert!(err.contains("broken.glb"), "{err}");
    let r = report("o1");
    assert_eq!(
        (r["files"].as_u64(), r["written"].as_u64(), r["failed"].as_u64()),
        (Some(4), Some(3), Some(1))
    );
    let scenes: Vec<&str> =
        r["entries"].as_array().unwrap().iter().map(|e| e["scene"].as_str().unwrap()).collect();
    assert_eq!(scenes, ["a_000", "broken_001", "b_002", "c_003"]);
    let broken = &r["entries"][1];
    assert_eq!(broken["status"], "failed");
    assert!(broken["reason"].as_str().unwrap().contains("broken.glb"), "{broken}");
    assert!(!dir.join("o1/broken_001").exists());

    // A re-run keeps what was written and redoes only what failed.
    let before = tree(&dir.join("o1/c_003"));
    let again = run(&[input_arg], "o1");
    let out = String::from_utf8_lossy(&again.stdout);
    assert!(out.contains("keeping 3 scene(s)"), "{out}");
    let r = report("o1");
    assert_eq!(
        (r["kept"].as_u64(), r["written"].as_u64(), r["failed"].as_u64()),
        (Some(3), Some(0), Some(1))
    );
    assert_eq!(tree(&dir.join("o1/c_003")), before);

    // The same scenes from one import thread: the number of threads changes nothing.
    let _ = run(&[input_arg, "--jobs", "1"], "o2");
    let scenes = |out: &str| -> Vec<(String, Vec<u8>)> {
        tree(&dir.join(out)).into_iter().filter(|(p, _)| p != "report.json").collect()
    };
    assert_eq!(scenes("o1"), scenes("o2"));

    // A list of files, relative to the list's folder, with comments and blank lines.
    std::fs::write(dir.join("files.txt"), "# two of them\nin/a.gltf\n\nin/sub/c.gltf\n").unwrap();
    let listed = run(&["--list", dir.join("files.txt").to_str().unwrap()], "o3");
    assert!(listed.status.success(), "{}", String::from_utf8_lossy(&listed.stderr));
    let r = report("o3");
    let scenes: Vec<&str> =
        r["entries"].as_array().unwrap().iter().map(|e| e["scene"].as_str().unwrap()).collect();
    assert_eq!(scenes, ["a_000", "c_001"]);

    // Nothing to import, or a path that is not there: errors that say so.
    std::fs::create_dir_all(dir.join("empty")).unwrap();
    let e = run(&[dir.join("empty").to_str().unwrap()], "o4");
    assert!(String::from_utf8_lossy(&e.stderr).contains("no .gltf or .glb file"));
    let e = run(&[dir.join("nowhere").to_str().unwrap()], "o4");
    assert!(String::from_utf8_lossy(&e.stderr).contains("no such file or folder"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn render_draws_spherical_harmonics_along_each_view() {
    // A 3D Gaussian splatting PLY with harmonics of degree 3: each frame equals the render of
    // the same Gaussians with the colours baked for that frame's camera centre (the f64
    // reference, on the host), to the 8-bit level; without the harmonics it does not.
    use std::path::Path;
    use velox_engine::ops::raster::GaussianData;
    use velox_engine::rng::Rng;
    use velox_io::ply;
    let dir = std::env::temp_dir().join(format!("velox-render-sh-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut rng = Rng::new(17);
    let n = 400;
    let g = GaussianData {
        means: rng.uniform_vec(3 * n, -0.6, 0.6),
        log_scales: rng.uniform_vec(3 * n, -3.5, -2.5),
        quats: rng.normal_vec(4 * n),
        opacities: rng.uniform_vec(n, 0.0, 3.0),
        colours: rng.uniform_vec(3 * n, 0.2, 0.8),
    };
    let k = ply::Sh::per_channel(3);
    let sh = ply::Sh { degree: 3, coeffs: rng.uniform_vec(3 * k * n, -0.4, 0.4) };
    let with_sh = dir.join("sh.ply");
    std::fs::write(&with_sh, ply::to_bytes_sh(&g, Some(&sh)).unwrap()).unwrap();
    let render = |ply: &Path, out: &Path| {
        let run = velox()
            .arg("render")
            .arg(ply)
            .arg("--out")
            .arg(out)
            .args(["--frames", "2", "--width", "48", "--height", "32", "--no-depth"])
            .output()
            .unwrap();
        assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
        String::from_utf8_lossy(&run.stdout).into_owned()
    };
    let drawn = dir.join("drawn");
    assert!(render(&with_sh, &drawn).contains("spherical harmonics of degree 3"));
    let listing: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(drawn.join("render.json")).unwrap()).unwrap();
    let frame = |folder: &Path, i: usize| {
        velox_io::image::read_png(&folder.join(format!("frame_{i:04}.png"))).unwrap().0
    };
    let worst = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    for i in 0..2 {
        let eye: Vec<f32> =
            listing[i]["eye"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
        let mut baked = g.clone();
        for j in 0..n {
            let d: [f64; 3] = std::array::from_fn(|a| (g.means[3 * j + a] - eye[a]) as f64);
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let base = [0, 1, 2].map(|c| g.colours[3 * j + c]);
            let c = ply::sh_colour(base, &sh.coeffs[j * 3 * k..(j + 1) * 3 * k], 3, d.map(|v| v / l));
            for (to, v) in baked.colours[3 * j..3 * j + 3].iter_mut().zip(c) {
                *to = v as f32;
            }
        }
        let (baked_ply, baked_out) = (dir.join(format!("baked{i}.ply")), dir.join(format!("baked{i}")));
        ply::write(&baked_ply, &baked).unwrap();
        render(&baked_ply, &baked_out);
        let e = worst(&frame(&drawn, i), &frame(&baked_out, i));
        assert!(e <= 1.5 / 255.0, "frame {i}: {e} from the baked colours");
    }
    let plain = dir.join("plain.ply");
    ply::write(&plain, &g).unwrap();
    render(&plain, &dir.join("plain"));
    assert!(
        worst(&frame(&drawn, 0), &frame(&dir.join("plain"), 0)) > 10.0 / 255.0,
        "the harmonics were not drawn"
    );
    std::fs::remove_dir_all(&dir).ok();
}
