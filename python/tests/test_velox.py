"""The Python package against the command line on the same inputs (the same PLY bytes, the
same pixels, the same tokens and checkpoints), and its refusals of bad input.

Runs in a fresh venv with the package installed (`tools/test.sh` does it); the `velox`
command is `VELOX_BIN`, else the repository's `target/release/velox`."""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

import velox

ROOT = Path(__file__).resolve().parents[2]
VELOX = os.environ.get("VELOX_BIN", str(ROOT / "target" / "release" / "velox"))


def cli(*args):
    """Runs the velox command; fails the test with its stderr when it fails."""
    run = subprocess.run([VELOX, *map(str, args)], capture_output=True, text=True)
    assert run.returncode == 0, f"velox {' '.join(map(str, args))}:\n{run.stderr}"
    return run


def random_gaussians(n=300, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.standard_normal((n, 4)).astype(np.float32)
    return {
        "means": (rng.standard_normal((n, 3)) * 0.6).astype(np.float32),
        "scales": rng.uniform(0.02, 0.12, (n, 3)).astype(np.float32),
        "quats": q / np.linalg.norm(q, axis=1, keepdims=True),
        "opacities": rng.uniform(0.2, 0.95, n).astype(np.float32),
        "colors": rng.random((n, 3)).astype(np.float32),
    }


def to_rgb8(rgb):
    """8-bit values as the PNG writer makes them: clamp, times 255 in float32, halves up."""
    y = np.clip(rgb, 0, 1).astype(np.float32) * np.float32(255)
    return np.where(y - np.floor(y) == 0.5, np.floor(y) + 1, np.round(y)).astype(np.uint8)


def points_ply(path):
    """The float rows of a binary little-endian PLY of float properties only."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    names = [l.split()[-1] for l in data[:end].decode().splitlines() if l.startswith("property")]
    return np.frombuffer(data[end:], dtype="<f4").reshape(-1, len(names)), names


@pytest.fixture(scope="session")
def dataset(tmp_path_factory):
    """Two small procedural scenes, written by Python and by the command line."""
    root = tmp_path_factory.mktemp("data")
    options = dict(scenes=2, seed=3, res=24, points=1500, tracks=64, supersample=1)
    dirs = velox.data.synth(root / "py", progress=False, **options)
    cli("data", "synth", "--out", root / "cli", "--scenes", 2, "--seed", 3, "--res", 24,
        "--points", 1500, "--tracks", 64, "--supersample", 1)
    return root, dirs


@pytest.fixture(scope="session")
def trained(dataset, tmp_path_factory):
    """A tiny autoencoder trained 3 steps from Python, and the same run from the command line
    (Python's recording each step while the last runs, the command's after the last's wait)."""
    root, _ = dataset
    runs = tmp_path_factory.mktemp("runs")
    events = []
    out = velox.train("autoencoder", root / "py", runs / "py", config="tiny", steps=3, seed=5,
                      precision="f32", progress=events.append, overlap=True)
    cli("train", "autoencoder", "--data", root / "cli", "--out", runs / "cli", "--config", "tiny",
        "--steps", 3, "--seed", 5, "--precision", "f32")
    return runs, out, events


def test_devices_and_the_default_device():
    listed = velox.devices()
    assert listed and {"index", "name", "kind", "api_version", "unusable"} <= set(listed[0])
    assert velox.Device().name == velox.Device(0).name == listed[0]["name"] or any(
        d["unusable"] for d in listed)
    with pytest.raises(ValueError, match="matches none"):
        velox.Device("no such device")


def test_gaussians_pass_through_a_ply_to_the_bit(tmp_path):
    g = random_gaussians()
    velox.write_gaussians(tmp_path / "a.ply", g)
    raw = velox.read_gaussians(tmp_path / "a.ply", raw=True)
    assert set(raw) == {"means", "log_scales", "quats", "opacity_logits", "colors"}
    velox.write_gaussians(tmp_path / "b.ply", raw)
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    back = velox.read_gaussians(tmp_path / "a.ply")
    for key, value in g.items():
        assert back[key].dtype == np.float32 and back[key].shape == value.shape
        np.testing.assert_allclose(back[key], value, rtol=1e-6, atol=1e-6)


def test_a_render_has_the_pixels_of_velox_render(tmp_path):
    # With spherical harmonics of degree 2: both draw them along each view.
    g = random_gaussians()
    g["sh"] = np.random.default_rng(4).uniform(-0.3, 0.3, (300, 3, 8)).astype(np.float32)
    velox.write_gaussians(tmp_path / "g.ply", g)
    cli("render", tmp_path / "g.ply", "--out", tmp_path / "r", "--frames", 2, "--width", 40,
        "--height", 24, "--radius", 3, "--background", "0.2,0.3,0.4")
    frames = json.loads((tmp_path / "r" / "render.json").read_text())
    g = velox.read_gaussians(tmp_path / "g.ply")
    for frame in frames:
        c = frame["camera"]
        w2c = np.eye(4)
        w2c[:3, :3] = c["rotation"]
        w2c[:3, 3] = c["translation"]
        cam = {"world_to_camera": w2c, "fx": c["fx"], "fy": c["fy"], "cx": c["cx"], "cy": c["cy"]}
        rgb, alpha, depth = velox.render(g, cam, c["width"], c["height"], background=(0.2, 0.3, 0.4),
                                         alpha=True, depth=True)
        assert rgb.shape == (24, 40, 3) and alpha.shape == depth.shape == (24, 40)
        png = velox.read_image(tmp_path / "r" / frame["png"])
        assert np.array_equal(to_rgb8(rgb), to_rgb8(png)), frame["png"]
        assert alpha.max() > 0.5 and 2.0 < depth[alpha > 0.5].mean() < 4.0
        plain = velox.render({k: v for k, v in g.items() if k != "sh"}, cam, c["width"], c["height"],
                             background=(0.2, 0.3, 0.4))
        assert np.abs(plain - rgb).max() > 0.05, "the harmonics were drawn"


def test_the_data_is_the_commands_byte_for_byte(dataset):
    root, dirs = dataset
    assert [d.name for d in map(Path, dirs)] == ["scene_00003", "scene_00004"]
    for scene in dirs:
        scene = Path(scene)
        for f in sorted(p for p in scene.rglob("*") if p.is_file()):
            twin = root / "cli" / scene.name / f.relative_to(scene)
            assert f.read_bytes() == twin.read_bytes(), f
    cloud = velox.data.read_cloud(dirs[0])
    assert cloud.dtype == np.float32 and cloud.shape == (1500, 7)


def test_a_training_run_is_the_commands_bit_for_bit(trained):
    runs, out, events = trained
    assert out["step"] == out["steps"] == 3 and out["stopped"] is None and out["seed"] == 5
    a = (runs / "py" / "checkpoint.safetensors").read_bytes()
    b = (runs / "cli" / "checkpoint.safetensors").read_bytes()
    assert a == b, "the checkpoints of the same run from Python and from the command line differ"
    kinds = [e["event"] for e in events]
    assert kinds[0] == "begin" and kinds.count("step") == 3 and kinds[-1] == "end"
    assert all(np.isfinite(e["loss"]) for e in events if e["event"] == "step")


def test_a_run_resumes_and_refuses_what_would_change_it(trained, dataset):
    runs, _, _ = trained
    root, _ = dataset
    with pytest.raises(ValueError, match="`seed` 6 differs from the 5"):
        velox.train("autoencoder", root / "py", runs / "py", resume=True, seed=6, progress=False)
    with pytest.raises(ValueError, match="already holds a checkpoint: ask for `resume`"):
        velox.train("autoencoder", root / "py", runs / "py", config="tiny", progress=False)
    with pytest.raises(ValueError, match="at step 3 of a run of 3 steps: ask for more `steps`"):
        velox.train("autoencoder", root / "py", runs / "py", resume=True, progress=False)
    with pytest.raises(ValueError, match="`stop_at` 2 is not a step to come"):
        velox.train("autoencoder", root / "py", runs / "py", resume=True, steps=6, stop_at=2, progress=False)
    with pytest.raises(ValueError, match="resume and init exclude each other"):
        velox.train("autoencoder", root / "py", runs / "x", resume=True, init=runs / "py" / "checkpoint.safetensors")


def test_an_exception_in_progress_stops_the_run_with_its_checkpoint(dataset, tmp_path):
    root, _ = dataset

    def stop_at_the_second_step(event):
        if event["event"] == "step" and event["step"] == 2:
            raise RuntimeError("enough")

    with pytest.raises(RuntimeError, match="enough"):
        velox.train("autoencoder", root / "py", tmp_path / "run", config="tiny", steps=5,
                    progress=stop_at_the_second_step)
    assert (tmp_path / "run" / "checkpoint.safetensors").is_file()
    out = velox.train("autoencoder", root / "py", tmp_path / "run", resume=True, progress=False)
    assert out["step"] == 5


def test_encode_and_decode_are_the_commands(trained, dataset, tmp_path):
    runs, _, _ = trained
    _, dirs = dataset
    ckpt = runs / "py" / "checkpoint.safetensors"
    ae = velox.Autoencoder.load(ckpt)
    assert ae.config == "tiny"
    cloud = velox.data.read_cloud(dirs[0])
    tokens = ae.encode(cloud, seed=2)
    assert tokens.shape == ae.token_shape and tokens.dtype == np.float32
    assert np.array_equal(tokens, ae.encode(cloud, seed=2)), "the same seed, the same tokens"

    cli("decode", "points", "--checkpoint", ckpt, "--cloud", dirs[0], "--out", tmp_path / "p",
        "--frames", "0,5", "--seed", 2, "--points", 500, "--steps", 4, "--sampler", "euler")
    for frame in (0, 5):
        xyz = ae.decode_points(tokens, frame / 100, 500, steps=4, sampler="euler", seed=2)
        rows, names = points_ply(tmp_path / "p" / f"points_f{frame:02}.ply")
        assert names == ["x", "y", "z", "tau"]
        assert np.array_equal(xyz, rows[:, :3]), f"frame {frame}"

    for voxels in ("surface", "cloud"):
        out = tmp_path / voxels
        cli("decode", "gaussians", "--checkpoint", ckpt, "--cloud", dirs[0], "--out", out,
            "--frames", 3, "--seed", 2, "--points", 800, "--steps", 4, "--voxels", voxels)
        g = ae.decode_gaussians(tokens, 0.03, cloud=cloud if voxels == "cloud" else None,
                                points=800, steps=4, seed=2, raw=True)
        velox.write_gaussians(tmp_path / f"{voxels}.ply", g)
        assert (tmp_path / f"{voxels}.ply").read_bytes() == (out / "gaussians_f03.ply").read_bytes()
    with pytest.raises(ValueError, match="not a frame's time"):
        ae.decode_gaussians(tokens, 0.035)


@pytest.mark.parametrize("call, named", [
    (lambda g, c: velox.render({**g, "means": g["means"].astype(np.float64)}, c, 8, 8), r'gaussians\["means"\].*float64'),
    (lambda g, c: velox.render({**g, "quats": g["quats"][:, :3]}, c, 8, 8), r'gaussians\["quats"\].*\[300, 3\]'),
    (lambda g, c: velox.render({**g, "colors": g["colors"][:5]}, c, 8, 8), r'gaussians\["colors"\] has 5 rows'),
    (lambda g, c: velox.render({**g, "scales": -g["scales"]}, c, 8, 8), r"scales must be positive"),
    (lambda g, c: velox.render({**g, "opacities": np.ones(300, np.float32)}, c, 8, 8), r"opacities must lie in \(0, 1\)"),
    (lambda g, c: velox.render({k: v for k, v in g.items() if k != "colors"}, c, 8, 8), r'no "colors"'),
    (lambda g, c: velox.render(g, {**c, "fx": -1.0}, 8, 8), r"fx, fy must be positive"),
    (lambda g, c: velox.render(g, {**c, "world_to_camera": np.eye(3)}, 8, 8), r"must be 4 x 4"),
    (lambda g, c: velox.render(g, c, 0, 8), r"non-zero"),
    (lambda g, c: velox.render(g, "camera", 8, 8), r"camera must be a dict"),
    (lambda g, c: velox.metrics.chamfer(g["means"], g["quats"]), r"b must be a float32 array of shape \[N, 3\]"),
    (lambda g, c: velox.metrics.psnr(np.full((4, 4, 3), np.nan, np.float32), np.zeros((4, 4, 3), np.float32)), r"image\[0, 0, 0\] is NaN"),
    (lambda g, c: velox.write_gaussians("/nonexistent-dir/x.ply", g), r"x.ply"),
])
def test_bad_input_is_refused_naming_it(call, named):
    g = random_gaussians()
    w2c = np.eye(4)
    w2c[2, 3] = 3
    cam = {"world_to_camera": w2c, "fx": 10.0, "fy": 10.0, "cx": 4.0, "cy": 4.0}
    with pytest.raises((ValueError, OSError), match=named):
        call(g, cam)


def test_missing_files_are_file_not_found_errors(tmp_path):
    with pytest.raises(FileNotFoundError) as e:
        velox.read_gaussians(tmp_path / "missing.ply")
    assert e.value.filename == str(tmp_path / "missing.ply")
    with pytest.raises(FileNotFoundError):
        velox.Autoencoder.load(tmp_path / "missing.safetensors")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(ValueError, match="bad.ply"):
        velox.read_gaussians(tmp_path / "bad.ply")


def test_metrics_on_arrays():
    a = np.zeros((16, 16, 3), np.float32)
    b = np.full((16, 16, 3), 0.1, np.float32)
    assert velox.metrics.psnr(a, b) == pytest.approx(20.0, abs=1e-5)
    assert velox.metrics.ssim(b, b) == pytest.approx(1.0)
    p = np.array([[0, 0, 0], [1, 0, 0]], np.float32)
    q = np.array([[0, 0, 0.5]], np.float32)
    # a -> b: (0.25 + 1.25) / 2; b -> a: 0.25.
    assert velox.metrics.chamfer(p, q) == pytest.approx(1.0)
    rng = np.random.default_rng(1)
    truth = (rng.random((8, 24, 3)) + [0, 0, 2]).astype(np.float32)
    visible = rng.random((8, 24)) > 0.2
    perfect = velox.metrics.tapvid3d(truth, visible, truth, visible, (200.0, 200.0, 128.0, 128.0), (256, 256))
    assert perfect["average_jaccard"] == pytest.approx(1.0) and perfect["occlusion_accuracy"] == 1.0
    off = velox.metrics.tapvid3d(truth + 0.3, visible, truth, visible, (200.0, 200.0, 128.0, 128.0),
                                 (256, 256), scaling="none")
    assert off["average_jaccard"] < perfect["average_jaccard"]
    with pytest.raises(ValueError, match="pred_visible must be a bool array"):
        velox.metrics.tapvid3d(truth, visible.astype(np.float32), truth, visible, (1.0, 1.0, 0.0, 0.0), (8, 8))


def test_video_tokens_and_tracks_are_the_commands(trained, dataset, tmp_path):
    runs, _, _ = trained
    root, dirs = dataset
    ae = runs / "py" / "checkpoint.safetensors"
    stored = velox.encode_dataset(ae, root / "py", source="video", video_points=3000, seed=1)
    assert stored["encoded"] == ["scene_00003", "scene_00004"] and stored["kept"] == []
    cli("encode", "--checkpoint", ae, "--data", root / "cli", "--source", "video", "--video-points", 3000,
        "--seed", 1)
    for name in stored["encoded"]:
        mine = sorted((Path(stored["dir"])).glob(f"{name}*"))
        assert mine, name
        for f in mine:
            assert f.read_bytes() == (root / "cli" / "tokens-video" / f.name).read_bytes(), f.name

    out = velox.train("tracker", root / "py", tmp_path / "tracker", config="tiny", steps=2, seed=1,
                      progress=False)
    tracker = velox.Tracker.load(out["checkpoint"], ae)
    tracked = tracker.track(dirs[0], grid=12, points=3000, seed=1)
    q = len(tracked["queries"])
    assert q > 0 and tracked["tracks"].shape == (q, 24, 3) and tracked["visible"].shape == (q, 24)
    assert tracked["visible"].dtype == np.bool_
    cli("track", "--video", dirs[0], "--autoencoder", ae, "--checkpoint", out["checkpoint"], "--out",
        tmp_path / "t", "--grid", 12, "--points", 3000, "--seed", 1)
    written = json.loads((tmp_path / "t" / "tracks.json").read_text())["queries"]
    assert np.array_equal(tracked["queries"], np.array([w["query"] for w in written], np.float32))
    assert np.array_equal(tracked["tracks"], np.array([w["positions"] for w in written], np.float32))
    assert np.array_equal(tracked["visible"], np.array([w["visible"] for w in written]))
    with pytest.raises(ValueError, match=r'video\["depth"\] must be a float32 array of shape \[24, 8, 8\]'):
        tracker.track({"rgb": np.zeros((24, 8, 8, 3), np.float32), "depth": np.zeros((24, 8, 9), np.float32),
                       "camera": {}})


def test_ctrl_c_stops_a_run_with_its_checkpoint(dataset, tmp_path):
    import signal
    import sys

    root, _ = dataset
    script = (
        "import sys, velox\n"
        "def told(e):\n"
        "    if e['event'] == 'step':\n"
        "        print('step', e['step'], flush=True)\n"
        f"velox.train('autoencoder', {str(root / 'py')!r}, {str(tmp_path / 'run')!r}, config='tiny',\n"
        "            steps=1000, progress=told)\n"
    )
    run = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True)
    assert run.stdout.readline().split() == ["step", "1"]
    run.send_signal(signal.SIGINT)
    _, err = run.communicate(timeout=300)
    assert run.returncode != 0 and "KeyboardInterrupt: stopped after step" in err, err
    assert "continue with resume=True" in err and (tmp_path / "run" / "checkpoint.safetensors").is_file()


def safetensors_f32(path):
    """The float32 tensors of a safetensors file, by name."""
    import struct

    data = Path(path).read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + n])
    body = data[8 + n:]
    out = {}
    for name, t in header.items():
        if name != "__metadata__":
            assert t["dtype"] == "F32", (name, t["dtype"])
            a, b = t["data_offsets"]
            out[name] = np.frombuffer(body[a:b], dtype="<f4").reshape(t["shape"])
    return out


def test_generated_tokens_are_the_commands(trained, dataset, tmp_path):
    runs, _, _ = trained
    root, dirs = dataset
    ae = runs / "py" / "checkpoint.safetensors"
    velox.encode_dataset(ae, root / "py")
    out = velox.train("generator", root / "py", tmp_path / "gen", config="tiny", steps=2, progress=False)
    gen = velox.Generator.load(out["checkpoint"], ae)
    assert gen.task == "video"
    tokens = gen.generate(dirs[0], steps=3, guidance=2.0, seed=4)
    cli("generate", "--checkpoint", out["checkpoint"], "--autoencoder", ae, "--video", dirs[0], "--out",
        tmp_path / "g", "--steps", 3, "--guidance", 2.0, "--seed", 4, "--frames", 0, "--views", 0,
        "--points", 300)
    (written,) = safetensors_f32(tmp_path / "g" / "tokens.safetensors").values()
    assert tokens.shape == written.shape and np.array_equal(tokens, written)
    # The frames as arrays (8-bit, as the PNGs hold them) give the same tokens.
    frames = np.stack([velox.read_image(Path(dirs[0]) / "video" / f"f{f:02}.png") for f in range(24)])
    assert np.array_equal(gen.generate(frames, steps=3, guidance=2.0, seed=4), tokens)
    with pytest.raises(ValueError, match="this generator reads 24 frame"):
        gen.generate(frames[:3])
    with pytest.raises(ValueError, match="reads videos"):
        gen.generate(Path(dirs[0]) / "video" / "f00.png")


def test_the_viewer_is_the_commands(tmp_path):
    import urllib.request

    ply = tmp_path / "g.ply"
    velox.write_gaussians(ply, random_gaussians())
    assert velox.view(ply, html=tmp_path / "a.html") == tmp_path / "a.html"
    cli("view", ply, "--html", tmp_path / "b.html")
    assert (tmp_path / "a.html").read_bytes() == (tmp_path / "b.html").read_bytes()

    url = velox.view([random_gaussians(seed=1), random_gaussians(seed=2)], open_browser=False)
    manifest = json.loads(urllib.request.urlopen(url + "manifest.json", timeout=30).read())
    assert manifest["kind"] == "gaussians" and len(manifest["frames"]) == 2
    body = urllib.request.urlopen(url + "frames/1.bin", timeout=30).read()
    assert body[:4] == b"VXG1" and int.from_bytes(body[4:8], "little") == 300
    # Another tool's numbered sequence opens as the command opens it.
    seq = tmp_path / "seq"
    seq.mkdir()
    for f in (0, 5):
        velox.write_gaussians(seq / f"frame_{f:04}.ply", random_gaussians(seed=f))
    velox.view(seq, html=tmp_path / "s.html")
    cli("view", seq, "--html", tmp_path / "t.html")
    assert (tmp_path / "s.html").read_bytes() == (tmp_path / "t.html").read_bytes()
    with pytest.raises(FileNotFoundError):
        velox.view(tmp_path / "missing", html=tmp_path / "c.html")
    with pytest.raises(ValueError, match="a dict of Gaussians"):
        velox.view(42)


def test_gltf_scenes_are_the_commands(tmp_path):
    skin = ROOT / "tests" / "fixtures" / "gltf" / "SimpleSkin.gltf"
    bad = tmp_path / "broken.gltf"
    bad.write_text("{not json")
    options = dict(res=16, points=800, tracks=16, supersample=1)
    made = velox.data.gltf([skin, bad], tmp_path / "py", progress=False, **options)
    assert [Path(p).name for p in made["written"]] == ["SimpleSkin_000"] and made["kept"] == []
    assert list(made["failed"]) == [str(bad)]
    cli("data", "gltf", skin, "--out", tmp_path / "cli", "--res", 16, "--points", 800, "--tracks", 16,
        "--supersample", 1)
    for f in sorted(p for p in (tmp_path / "py" / "SimpleSkin_000").rglob("*") if p.is_file()):
        twin = tmp_path / "cli" / "SimpleSkin_000" / f.relative_to(tmp_path / "py" / "SimpleSkin_000")
        assert f.read_bytes() == twin.read_bytes(), f
    again = velox.data.gltf(skin, tmp_path / "py", progress=False, **options)
    assert [Path(p).name for p in again["kept"]] == ["SimpleSkin_000"] and again["written"] == []


def fake_jpeg(width, height):
    """The start of a baseline JPEG whose frame header gives its size (all the benchmark's
    evaluation reads of its images)."""
    import struct

    app0 = b"\xff\xe0" + struct.pack(">H", 16) + b"JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00"
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, height, width, 3) + b"\x01\x11\x00\x02\x11\x01\x03\x11\x01"
    return b"\xff\xd8" + app0 + sof + b"\xff\xd9"


@pytest.mark.parametrize("save", [np.savez, np.savez_compressed])
def test_tapvid3d_files_are_scored_as_the_arrays_are(tmp_path, save):
    rng = np.random.default_rng(7)
    t, n = 12, 9
    truth = (rng.random((t, n, 3)) + [0, 0, 2]).astype(np.float32)       # time-major, as the files
    visible = rng.random((t, n)) > 0.25
    pred = truth + rng.normal(0, 0.02, truth.shape).astype(np.float32)
    pred_visible = visible ^ (rng.random((t, n)) > 0.9)
    q = rng.integers(0, t, n)
    queries = np.stack([rng.random(n) * 640, rng.random(n) * 480, q], axis=1).astype(np.float32)
    images = np.empty(t, dtype=object)
    images[:] = [fake_jpeg(640, 480)] * t
    intrinsics = np.array([500.0, 510.0, 320.0, 240.0], np.float32)
    (tmp_path / "gt").mkdir()
    (tmp_path / "pred").mkdir()
    save(tmp_path / "gt" / "clip.npz", tracks_XYZ=truth, visibility=visible, queries_xyt=queries,
         fx_fy_cx_cy=intrinsics, images_jpeg_bytes=images)
    save(tmp_path / "pred" / "clip.npz", tracks_XYZ=pred, visibility=pred_visible)
    scalings = ["median", "per_trajectory", "median_on_queries", "none"]
    got = velox.metrics.tapvid3d_files([tmp_path / "gt" / "clip.npz"], [tmp_path / "pred" / "clip.npz"],
                                       scalings=scalings)
    for s in scalings:
        want = velox.metrics.tapvid3d(pred.transpose(1, 0, 2).copy(), pred_visible.T.copy(),
                                      truth.transpose(1, 0, 2).copy(), visible.T.copy(),
                                      tuple(map(float, intrinsics)), (640, 480), scaling=s,
                                      query_frames=[int(f) for f in q])
        assert got["clips"][0][s] == want == got["mean"][s], s
    frame0 = velox.metrics.tapvid3d(pred.transpose(1, 0, 2).copy(), pred_visible.T.copy(),
                                    truth.transpose(1, 0, 2).copy(), visible.T.copy(),
                                    tuple(map(float, intrinsics)), (640, 480), scaling="per_trajectory")
    assert frame0 != got["mean"]["per_trajectory"], "the query frames change the per-trajectory scaling"

    run = cli("eval", "tapvid3d", tmp_path / "gt", "--predictions", tmp_path / "pred", "--scaling",
              "median,per_trajectory", "--out", tmp_path / "m.json")
    written = json.loads((tmp_path / "m.json").read_text())
    assert written["mean"]["median"]["average_jaccard"] == got["mean"]["median"]["average_jaccard"]
    assert "mean of 1 clip(s)" in run.stdout

    save(tmp_path / "pred" / "bad.npz", tracks_XYZ=pred[:, :3], visibility=pred_visible)
    with pytest.raises(ValueError, match=r"tracks_XYZ has shape \[12, 3, 3\], expected \[12, 9, 3\]"):
        velox.metrics.tapvid3d_files([tmp_path / "gt" / "clip.npz"], [tmp_path / "pred" / "bad.npz"])
    save(tmp_path / "gt" / "nokey.npz", tracks_XYZ=truth)
    with pytest.raises(ValueError, match="no visibility array"):
        velox.metrics.tapvid3d_files([tmp_path / "gt" / "nokey.npz"], [tmp_path / "pred" / "clip.npz"])



def test_an_rgbd_capture_is_imported_as_the_command_does_and_tracked(trained, dataset, tmp_path):
    import shutil

    root, dirs = dataset
    video = Path(dirs[0]) / "video"
    cams = json.loads((Path(dirs[0]) / "cameras.json").read_text())["video"]
    capture = tmp_path / "capture"
    (capture / "rgb").mkdir(parents=True)
    (capture / "depth").mkdir()
    for f in range(24):
        shutil.copy(video / f"f{f:02}.png", capture / "rgb" / f"{f:04}.png")
        shutil.copy(video / f"f{f:02}_depth.exr", capture / "depth" / f"{f:04}.exr")
    (capture / "intrinsics.json").write_text(json.dumps({k: cams[k] for k in ["fx", "fy", "cx", "cy", "width", "height"]}))
    record = velox.data.import_rgbd(capture, tmp_path / "py")
    assert record["windows"][0]["frames"] == list(range(24)) and record["scale"] > 0
    cli("import", "rgbd", capture, "--out", tmp_path / "cli")
    for f in sorted((tmp_path / "py").iterdir()):
        if f.name != "capture.json":
            assert f.read_bytes() == (tmp_path / "cli" / f.name).read_bytes(), f.name
    runs, _, _ = trained
    ae = runs / "py" / "checkpoint.safetensors"
    velox.encode_dataset(ae, root / "py", source="video", video_points=3000, seed=1)  # kept if stored
    out = velox.train("tracker", root / "py", tmp_path / "tracker", config="tiny", steps=1, progress=False)
    tracked = velox.Tracker.load(out["checkpoint"], ae).track(tmp_path / "py", grid=8, points=2000)
    assert tracked["tracks"].shape[1:] == (24, 3) and np.isfinite(tracked["tracks"]).all()
    assert tracked["frames"] == list(range(24))
    # The import is a 4D cloud too: its frames back-projected, every time of the clip.
    cloud = velox.data.read_cloud(tmp_path / "py")
    assert cloud.shape[1] == 7 and np.abs(cloud[:, :3]).max() <= 1.0
    assert np.array_equal(np.unique(cloud[:, 6]), np.arange(24, dtype=np.float32) / np.float32(100))
    # A longer capture in windows is tracked over all its frames.
    longer = tmp_path / "longer"
    (longer / "rgb").mkdir(parents=True)
    (longer / "depth").mkdir()
    for k in range(30):
        f = k * 23 // 29
        shutil.copy(video / f"f{f:02}.png", longer / "rgb" / f"{k:04}.png")
        shutil.copy(video / f"f{f:02}_depth.exr", longer / "depth" / f"{k:04}.exr")
    shutil.copy(capture / "intrinsics.json", longer / "intrinsics.json")
    record = velox.data.import_rgbd(longer, tmp_path / "windows", windows=4, fps=30.0)
    assert [w["dir"] for w in record["windows"]] == ["window_000", "window_001"]
    assert record["windows"][1]["frames"][0] == 6 and record["windows"][1]["times"][0] == 0.2
    tracker = velox.Tracker.load(out["checkpoint"], ae)
    clip = tracker.track(tmp_path / "windows", grid=8, points=2000)
    assert clip["frames"] == list(range(30)) and clip["tracks"].shape[1:] == (30, 3)
    with pytest.raises(ValueError, match="2 windows"):
        velox.data.read_cloud(tmp_path / "windows")
    cli("track", "--video", tmp_path / "windows", "--autoencoder", ae, "--checkpoint", out["checkpoint"],
        "--out", tmp_path / "t", "--grid", 8, "--points", 2000)
    written = json.loads((tmp_path / "t" / "tracks.json").read_text())
    assert written["source_frames"] == clip["frames"] and written["frames"] == 30
    assert np.array_equal(clip["tracks"], np.array([w["positions"] for w in written["queries"]], np.float32))
    assert np.array_equal(clip["visible"], np.array([w["visible"] for w in written["queries"]]))
    assert (tmp_path / "t" / "overlay" / "f29.png").is_file() and (tmp_path / "t" / "tracks_f29.ply").is_file()
    with pytest.raises(FileNotFoundError, match="intrinsics.json"):
        velox.data.import_rgbd(tmp_path / "py", tmp_path / "x")
    shutil.copy(capture / "intrinsics.json", tmp_path / "py" / "intrinsics.json")
    with pytest.raises(ValueError, match="no rgb/"):
        velox.data.import_rgbd(tmp_path / "py", tmp_path / "x")


def test_a_background_is_the_commands(tmp_path):
    options = dict(scenes=1, seed=9, res=16, points=300, tracks=4, supersample=1)
    (scene,) = velox.data.synth(tmp_path / "py", background=(1.0, 1.0, 1.0), progress=False, **options)
    cli("data", "synth", "--out", tmp_path / "cli", "--scenes", 1, "--seed", 9, "--res", 16, "--points", 300,
        "--tracks", 4, "--supersample", 1, "--background", "1,1,1")
    for f in sorted(p for p in Path(scene).rglob("*") if p.is_file()):
        assert f.read_bytes() == (tmp_path / "cli" / "scene_00009" / f.relative_to(scene)).read_bytes(), f
    assert json.loads((Path(scene) / "meta.json").read_text())["background"] == [1.0, 1.0, 1.0]
    with pytest.raises(ValueError, match="each channel must lie in"):
        velox.data.synth(tmp_path / "bad", background=(2.0, 0.0, 0.0), progress=False, **options)


def test_meshes_exports_and_videos_are_the_commands(tmp_path):
    # A mesh of points on a sphere: closed, facing out, through every file format.
    rng = np.random.default_rng(4)
    v = rng.standard_normal((20000, 3))
    points = (0.5 * v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)
    mesh = velox.mesh_of_points(points, resolution=40)
    p, t = mesh["positions"], mesh["triangles"]
    assert p.dtype == np.float32 and t.dtype == np.uint32 and t.shape[1] == 3
    radius = np.linalg.norm(p, axis=1)
    assert np.abs(radius - 0.5).max() < 0.25 * 1.0 / 40
    a, b, c = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    assert abs(volume / (4 / 3 * np.pi * 0.125) - 1) < 0.05
    for ext in ["ply", "obj", "glb"]:
        velox.write_mesh(tmp_path / f"sphere.{ext}", mesh)
        back = velox.read_mesh(tmp_path / f"sphere.{ext}")
        assert np.array_equal(back["positions"], p) and np.array_equal(back["triangles"], t), ext
    with pytest.raises(ValueError, match="uint32"):
        velox.write_mesh(tmp_path / "x.ply", {"positions": p, "triangles": t.astype(np.int64)})
    with pytest.raises(ValueError, match=".ply, .obj or .glb"):
        velox.write_mesh(tmp_path / "x.stl", mesh)

    # Per-frame Gaussians exported as the command exports them, byte for byte.
    frames = tmp_path / "frames"
    frames.mkdir()
    for f in [0, 5]:
        velox.write_gaussians(frames / f"gaussians_f{f:02}.ply", random_gaussians(200, seed=f))
    for to in ["ply-seq", "splatv", "spz", "glb"]:
        # A folder, or the .splatv file.
        place = "clip.splatv" if to == "splatv" else to
        files = velox.export(frames, to, out=tmp_path / "py" / place)
        cli("export", frames, "--to", to, "--out", tmp_path / "cli" / place)
        assert len(files) == (1 if to == "splatv" else 2)
        for f in files:
            twin = Path(str(f).replace(str(tmp_path / "py"), str(tmp_path / "cli")))
            assert Path(f).read_bytes() == twin.read_bytes(), f
    with pytest.raises(ValueError, match="`to`"):
        velox.export(frames, "obj")

    # A video file's frames through ffmpeg, as the command imports them.
    video = tmp_path / "video"
    video.mkdir()
    for k in range(6):
        velox.write_image(video / f"f{k:02}.png", rng.random((16, 24, 3)).astype(np.float32))
    subprocess.run(["ffmpeg", "-v", "error", "-framerate", "12", "-i", video / "f%02d.png", "-c:v", "ffv1",
                    "-pix_fmt", "bgr0", tmp_path / "clip.mkv"], check=True)
    r = velox.data.import_video(tmp_path / "clip.mkv", tmp_path / "py-frames")
    assert (r["frames"], r["width"], r["height"], r["fps"], r["capture"]) == (6, 24, 16, 12.0, None)
    cli("import", "video", tmp_path / "clip.mkv", "--out", tmp_path / "cli-frames")
    for k in range(6):
        name = f"frame_{k:05}.png"
        ours = (tmp_path / "py-frames" / name).read_bytes()
        assert ours == (tmp_path / "cli-frames" / name).read_bytes()
        assert np.array_equal(velox.read_image(tmp_path / "py-frames" / name),
                              velox.read_image(video / f"f{k:02}.png")), "lossless"
    with pytest.raises(ValueError, match="not empty"):
        velox.data.import_video(tmp_path / "clip.mkv", tmp_path / "py-frames")


def test_spherical_harmonics_pass_through_and_export(tmp_path):
    g = random_gaussians(50, seed=3)
    g["sh"] = np.random.default_rng(1).uniform(-0.3, 0.3, (50, 3, 8)).astype(np.float32)
    velox.write_gaussians(tmp_path / "sh.ply", g)
    back = velox.read_gaussians(tmp_path / "sh.ply")
    assert np.array_equal(back["sh"], g["sh"])
    # The command's viewer and exports take the same file: the PLY sequence keeps its bytes.
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "gaussians_f00.ply").write_bytes((tmp_path / "sh.ply").read_bytes())
    (seq,) = velox.export(frames, "ply-seq")
    assert Path(seq).read_bytes() == (tmp_path / "sh.ply").read_bytes()
    assert np.array_equal(velox.read_gaussians(seq)["sh"], g["sh"])
    with pytest.raises(ValueError, match="degrees 1, 2 and 3"):
        velox.write_gaussians(tmp_path / "x.ply", {**g, "sh": np.zeros((50, 3, 5), np.float32)})
