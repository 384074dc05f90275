//! `velox view` as a user meets it: what it refuses before serving, what it serves and what it
//! does not, the one-file page, and the page itself in a real browser (headless Chromium with
//! software WebGL2) against `velox render` of the same frame from the same camera; and
//! `velox export`, which writes the same frames for other viewers.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use velox_engine::ops::raster::GaussianData;
use velox_engine::rng::Rng;
use velox_io::decoded::{DecodeReport, DecodedFrame};
use velox_io::image::read_png;
use velox_io::splatv::SplatvCamera;
use velox_io::{frames, glb, ply, splatv, spz};

fn velox() -> Command {
    Command::new(env!("CARGO_BIN_EXE_velox"))
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("velox-view-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// `n` Gaussians around the origin (where the scenes' cameras look), of varied size, opacity
/// and colour, drawn from `seed`.
fn gaussians(n: usize, seed: u64) -> GaussianData {
    let mut rng = Rng::new(seed);
    let mut g = GaussianData::default();
    for _ in 0..n {
        let mean = [0; 3].map(|_| rng.range(-0.7, 0.7) as f32);
        let ls = [0; 3].map(|_| rng.range(-3.6, -2.2) as f32);
        let q = [0; 4].map(|_| rng.normal() as f32);
        let c = [0; 3].map(|_| rng.uniform() as f32);
        g.push(mean, ls, q, rng.range(-1.0, 3.0) as f32, c);
    }
    g
}

/// A dataset scene (for its cameras) and a decode-like folder of two Gaussian frames that names
/// it in its decode.json.
fn fixture(name: &str, res: u32, tracks: u32) -> (PathBuf, PathBuf) {
    let dir = temp_dir(name);
    let data = dir.join("data");
    let out = velox()
        .args(["data", "synth", "--scenes", "1", "--points", "2000", "--tracks"])
        .arg(tracks.to_string())
        .arg("--res")
        .arg(res.to_string())
        .arg("--out")
        .arg(&data)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let scene = data.join("scene_00000");
    let decoded = dir.join("decoded");
    std::fs::create_dir_all(&decoded).unwrap();
    for f in [0, 12] {
        ply::write(&decoded.join(format!("gaussians_f{f:02}.ply")), &gaussians(400, 3 + f as u64)).unwrap();
    }
    let frames = [0, 12]
        .map(|f| DecodedFrame {
            frame: f,
            tau: frames::tau_of(f),
            file: frames::frame_file("gaussians", f),
            count: 400,
            voxels: None,
            seconds: 0.0,
        })
        .to_vec();
    DecodeReport {
        command: "decode gaussians".into(),
        checkpoint: "checkpoint.safetensors".into(),
        cloud: scene.display().to_string(),
        config: "tiny".into(),
        precision: "f32".into(),
        input_points: 2000,
        voxels: Some("surface".into()),
        sampler: "heun".into(),
        steps: 8,
        points: 400,
        encode_seconds: 0.0,
        frames,
    }
    .write(&decoded)
    .unwrap();
    (scene, decoded)
}

/// A running `velox view` and its address; killed when dropped.
struct Server {
    child: Child,
    address: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn serve(path: &Path) -> Server {
    let mut child =
        velox().arg("view").arg(path).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let address = line
        .split_whitespace()
        .find_map(|w| w.strip_prefix("http://"))
        .unwrap_or_else(|| panic!("no address in {line:?}"))
        .trim_end_matches('/')
        .to_string();
    assert!(address.starts_with("127.0.0.1:"), "{address}");
    Server { child, address }
}

/// (status code, body) of a raw request.
fn request(address: &str, request_line: &str) -> (u32, Vec<u8>) {
    let mut s = TcpStream::connect(address).unwrap();
    write!(s, "{request_line}\r\nHost: {address}\r\n\r\n").unwrap();
    let mut reply = Vec::new();
    s.read_to_end(&mut reply).unwrap();
    let split = reply.windows(4).position(|w| w == b"\r\n\r\n").expect("a header");
    let head = String::from_utf8_lossy(&reply[..split]).to_string();
    let status = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    (status, reply[split + 4..].to_vec())
}

fn get(address: &str, path: &str) -> (u32, Vec<u8>) {
    request(address, &format!("GET {path} HTTP/1.1"))
}

/// The manifest a one-file page holds (the comments show its tag too: the manifest is the one
/// that holds an object).
fn manifest(page: &str) -> serde_json::Value {
    let tag = "<script id=\"velox-manifest\" type=\"application/json\">{";
    let json = &page[page.find(tag).unwrap() + tag.len() - 1..];
    let json = &json[..json.find("</script>").unwrap()].replace("<\\/", "</");
    serde_json::from_str(json).unwrap()
}

/// Each frame of a manifest and its count.
fn frame_counts(manifest: &serde_json::Value) -> Vec<(u64, u64)> {
    manifest["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| (f["frame"].as_u64().unwrap(), f["count"].as_u64().unwrap()))
        .collect()
}

fn fails(cmd: &mut Command) -> String {
    let out = cmd.output().unwrap();
    assert!(!out.status.success(), "succeeded: {}", String::from_utf8_lossy(&out.stdout));
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!err.contains("panicked"), "{err}");
    err
}

#[test]
fn bad_input_is_refused_before_anything_is_served() {
    let dir = temp_dir("bad");
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let err = fails(velox().arg("view").arg(&empty));
    assert!(err.contains("holds no frames"), "{err}");
    let err = fails(velox().arg("view").arg(dir.join("missing")));
    assert!(err.contains("does not exist"), "{err}");

    // A points PLY among Gaussian frames.
    let mixed = dir.join("mixed");
    std::fs::create_dir_all(&mixed).unwrap();
    ply::write(&mixed.join("gaussians_f00.ply"), &gaussians(10, 1)).unwrap();
    let points =
        "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
                  property float z\nend_header\n";
    let mut bytes = points.as_bytes().to_vec();
    bytes.extend_from_slice(&[0u8; 12]);
    std::fs::write(mixed.join("gaussians_f01.ply"), &bytes).unwrap();
    let err = fails(velox().arg("view").arg(&mixed));
    assert!(err.contains("gaussians_f01.ply") && err.contains("different formats"), "{err}");

    // A truncated frame.
    let cut = dir.join("cut");
    std::fs::create_dir_all(&cut).unwrap();
    let whole = ply::to_bytes(&gaussians(10, 2)).unwrap();
    std::fs::write(cut.join("gaussians_f00.ply"), &whole[..whole.len() - 7]).unwrap();
    let err = fails(velox().arg("view").arg(&cut));
    assert!(err.contains("gaussians_f00.ply") && err.contains("truncated"), "{err}");

    // A comparison that is not there.
    let err = fails(
        velox().arg("view").arg(mixed.join("gaussians_f00.ply")).arg("--compare").arg(dir.join("nope")),
    );
    assert!(err.contains("nope") && err.contains("does not exist"), "{err}");

    // A port in use.
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port().to_string();
    let err = fails(velox().arg("view").arg(mixed.join("gaussians_f00.ply")).args(["--port", &port]));
    assert!(err.contains(&format!("port {port}")) && err.contains("in use"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_server_answers_its_routes_and_nothing_outside_them() {
    let (scene, decoded) = fixture("serve", 32, 8);
    let server = serve(&decoded);
    let a = &server.address;
    let (status, page) = get(a, "/");
    assert_eq!(status, 200);
    assert!(String::from_utf8_lossy(&page).contains("viewer.js"));
    let (status, script) = get(a, "/viewer.js");
    assert_eq!(status, 200);
    // Nothing the page loads names another host: every request stays on 127.0.0.1.
    for text in [&page, &script] {
        let text = String::from_utf8_lossy(text);
        assert!(
            !text.contains("http://") && !text.contains("https://") && !text.contains("//cdn"),
            "an outside URL"
        );
    }
    let (status, manifest) = get(a, "/manifest.json");
    assert_eq!(status, 200);
    let m: serde_json::Value = serde_json::from_slice(&manifest).unwrap();
    assert_eq!(m["kind"], "gaussians");
    let frames = m["frames"].as_array().unwrap();
    assert_eq!((frames.len(), &frames[1]["frame"], &frames[1]["count"]), (2, &12.into(), &400.into()));
    assert!(m["cameras"].as_array().unwrap().len() > 1, "the scene's cameras");
    let (status, body) = get(a, "/frames/1.bin?cache=no");
    assert_eq!(status, 200);
    assert_eq!((&body[..4], body.len()), (&b"VXG1"[..], 8 + 400 * 13 * 4));
    assert_eq!(u32::from_le_bytes(body[4..8].try_into().unwrap()), 400);
    // Beside it the scene's ground-truth points, frame by frame, and its tracks.
    let truth = &m["compare"]["frames"];
    assert_eq!(truth.as_array().unwrap().len(), 24);
    let (status, body) = get(a, "/compare/12.bin");
    let points = truth[12]["count"].as_u64().unwrap() as usize;
    assert_eq!((status, &body[..4], body.len()), (200, &b"VXG1"[..], 8 + points * 13 * 4));
    assert_eq!((m["tracks"]["count"].as_u64(), m["tracks"]["frames"].as_u64()), (Some(8), Some(24)));
    let (status, body) = get(a, "/tracks.bin");
    assert_eq!((status, &body[..4], body.len()), (200, &b"VXT1"[..], 12 + 8 * 24 * 12 + 8 * 24));
    let first = f32::from_le_bytes(body[12..16].try_into().unwrap());
    let truth_tracks = velox_data::format::read_scene(&scene, false).unwrap().tracks;
    assert_eq!(first, truth_tracks[0][0][0], "track 0 at frame 0");
    assert_eq!(get(a, "/compare/24.bin").0, 404);
    // Nothing but the routes: no path leads into the folder or out of it.
    for path in [
        "/frames/2.bin",
        "/gaussians_f00.ply",
        "/../Cargo.toml",
        "/%2e%2e/%2e%2e/etc/passwd",
        "/frames/../decode.json",
    ] {
        assert_eq!(get(a, path).0, 404, "{path}");
    }
    assert_eq!(request(a, "POST /manifest.json HTTP/1.1").0, 405);
    // A frame that breaks while the server runs is an error the page can show.
    std::fs::write(decoded.join("gaussians_f12.ply"), b"ply\nformat ascii 1.0\nend_header\n").unwrap();
    let (status, why) = get(a, "/frames/1.bin");
    let why = String::from_utf8_lossy(&why);
    assert!(status == 500 && why.contains("gaussians_f12.ply"), "{status} {why}");
}

#[test]
fn html_writes_one_page_that_holds_every_frame() {
    let (scene, decoded) = fixture("html", 32, 8);
    let page = decoded.join("view.html");
    let out = velox().arg("view").arg(&decoded).arg("--html").arg(&page).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = std::fs::read_to_string(&page).unwrap();
    assert!(text.contains("id=\"velox-manifest\"") && text.contains("id=\"tracks\""));
    assert!(!text.contains("src=\"viewer.js\""), "the script is inline");
    assert!(!text.contains("http://") && !text.contains("https://"), "nothing fetched from outside");
    // Every frame the manifest names is in the page under the id its URL gives. Would catch:
    // the manifest naming `#frames-K` where the page holds `frame-K` (nothing drawn).
    let manifest = manifest(&text);
    let urls: Vec<String> = manifest["frames"]
        .as_array()
        .unwrap()
        .iter()
        .chain(manifest["compare"]["frames"].as_array().unwrap())
        .map(|f| f["url"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(urls.len(), 2 + 24, "two frames and the truth's 24");
    for url in &urls {
        let id = url.strip_prefix('#').unwrap_or_else(|| panic!("{url} is not in the page"));
        assert!(
            text.contains(&format!("id=\"{id}\"")),
            "the manifest names {url}, the page has no such element"
        );
    }
    // And the one-file page draws from disk what `velox render` draws of that frame.
    let dir = decoded.parent().unwrap().to_path_buf();
    let window = (32, 32);
    let one =
        screenshot(&format!("file://{}#camera=0&frame=1&ui=0", page.display()), window, &dir, "one-file.png");
    let want = rendered_f12(&decoded, &scene, &dir, window);
    assert!(want.iter().any(|&v| v > 0.1), "the frame is not empty");
    let p = psnr(&one, &want);
    assert!(p >= 30.0, "the one-file page against velox render: PSNR {p:.1} dB");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Headless Chromium with software WebGL2 (SwiftShader), at device scale 1.
fn chromium(window: (u32, u32), dir: &Path) -> Command {
    let mut c = Command::new("chromium");
    c.args([
        "--headless=new",
        "--no-sandbox",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--force-device-scale-factor=1",
        "--hide-scrollbars",
        "--virtual-time-budget=20000",
    ])
    .arg(format!("--window-size={},{}", window.0, window.1))
    .arg(format!("--user-data-dir={}", dir.join("profile").display()));
    c
}

fn screenshot(url: &str, window: (u32, u32), dir: &Path, name: &str) -> Vec<f32> {
    let png = dir.join(name);
    let out = chromium(window, dir).arg(format!("--screenshot={}", png.display())).arg(url).output();
    let out =
        out.expect("the browser test needs Chromium: apt-get install chromium (tools/setup.sh --tests does)");
    assert!(png.exists(), "no screenshot: {}", String::from_utf8_lossy(&out.stderr));
    let (rgb, w, h) = read_png(&png).unwrap();
    assert_eq!((w, h), window);
    rgb
}

fn dom(url: &str, dir: &Path) -> String {
    let out = chromium((256, 256), dir).arg("--dump-dom").arg(url).output().expect("Chromium");
    String::from_utf8_lossy(&out.stdout).to_string()
}

/// Frame 12 of `decoded` (`gaussians_f12.ply`) as `velox render` draws it from the scene's
/// camera 0, `window` pixels (checked).
fn rendered_f12(decoded: &Path, scene: &Path, dir: &Path, window: (u32, u32)) -> Vec<f32> {
    let render = dir.join("render");
    let out = velox()
        .arg("render")
        .arg(decoded.join("gaussians_f12.ply"))
        .arg("--scene")
        .arg(scene)
        .args(["--view", "0", "--no-depth", "--out"])
        .arg(&render)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (want, w, h) = read_png(&render.join("frame_0000.png")).unwrap();
    assert_eq!((w, h), window);
    want
}

fn psnr(a: &[f32], b: &[f32]) -> f64 {
    let mse = a.iter().zip(b).map(|(x, y)| (*x as f64 - *y as f64).powi(2)).sum::<f64>() / a.len() as f64;
    10.0 * (1.0 / mse.max(1e-12)).log10()
}

/// The `data-NAME` attribute of the page's body in a DOM dump.
fn body_attribute(dump: &str, name: &str) -> Option<String> {
    let body = &dump[dump.find("<body")?..];
    let body = &body[..body.find('>')?];
    let at = body.find(&format!("data-{name}=\""))? + name.len() + 7;
    Some(body[at..at + body[at..].find('"')?].to_string())
}

#[test]
fn the_page_draws_a_frame_as_velox_render_does_and_plays() {
    let (scene, decoded) = fixture("browser", 64, 0);
    let dir = decoded.parent().unwrap().to_path_buf();
    let server = serve(&decoded);
    let url = |hash: &str| format!("http://{}/index.html#{hash}", server.address);
    let window = (64, 64);

    // Frame 1 (clip frame 12) from scene camera 0, through the page's own controls.
    let page = screenshot(&url("camera=0&frame=1&ui=0"), window, &dir, "page.png");
    let want = rendered_f12(&decoded, &scene, &dir, window);
    let p = psnr(&page, &want);
    eprintln!("page against velox render: PSNR {p:.1} dB");
    assert!(p >= 30.0, "PSNR {p:.1} dB");

    // The slider changes the picture.
    let other = screenshot(&url("camera=0&frame=0&ui=0"), window, &dir, "other.png");
    assert!(psnr(&page, &other) < 25.0, "frames 0 and 12 look alike");

    // Playing advances the frames; a frame that fails shows its error on the page.
    let played = dom(&url("camera=0&play=1"), &dir);
    let drawn: usize = body_attribute(&played, "drawn").and_then(|d| d.parse().ok()).unwrap_or(0);
    assert!(drawn >= 2, "frames drawn while playing: {drawn}");
    std::fs::write(decoded.join("gaussians_f12.ply"), b"not a ply").unwrap();
    let broken = dom(&url("frame=1"), &dir);
    let error = body_attribute(&broken, "error").unwrap_or_default();
    assert!(error.contains("gaussians_f12.ply"), "the page shows: {error:?}");
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn another_tools_numbered_ply_sequence_opens_frame_by_frame() {
    // frame_0000.ply, frame_0005.ply, frame_0010.ply as another exporter names them: three
    // frames, numbered by their files, in number order whatever the names sort to.
    let dir = temp_dir("numbered");
    let seq = dir.join("seq");
    std::fs::create_dir_all(&seq).unwrap();
    for (f, n) in [(10, 7), (0, 5), (5, 6)] {
        ply::write(&seq.join(format!("frame_{f:04}.ply")), &gaussians(n, f as u64)).unwrap();
    }
    std::fs::write(seq.join("notes.txt"), "not a frame").unwrap();
    let page = dir.join("seq.html");
    let out = velox().arg("view").arg(&seq).arg("--html").arg(&page).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = std::fs::read_to_string(&page).unwrap();
    let manifest = manifest(&text);
    assert_eq!(manifest["kind"], "gaussians");
    assert_eq!(frame_counts(&manifest), [(0, 5), (5, 6), (10, 7)]);
    // Two sequences in one folder, or two files of one frame: errors naming them.
    ply::write(&seq.join("other_0001.ply"), &gaussians(3, 9)).unwrap();
    let err = fails(velox().arg("view").arg(&seq));
    assert!(err.contains("two sequences") && err.contains("other_0001.ply"), "{err}");
    std::fs::remove_file(seq.join("other_0001.ply")).unwrap();
    ply::write(&seq.join("frame_5.ply"), &gaussians(3, 9)).unwrap();
    let err = fails(velox().arg("view").arg(&seq));
    assert!(err.contains("frame_5.ply") && err.contains("both frame 5"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn export_writes_every_format_and_each_reads_back() {
    let (scene, decoded) = fixture("export", 32, 0);
    let source = |f: usize| decoded.join(frames::frame_file("gaussians", f));
    let clip = [0, 12].map(|f| ply::read(&source(f)).unwrap());
    // Frame 12 with spherical harmonics of degree 2, which SPZ and glTF carry.
    let sh =
        ply::Sh { degree: 2, coeffs: (0..clip[1].len() * 24).map(|i| (i % 7) as f32 * 0.1 - 0.3).collect() };
    std::fs::write(source(12), ply::to_bytes_sh(&clip[1], Some(&sh)).unwrap()).unwrap();
    for to in ["ply-seq", "splatv", "spz", "glb"] {
        let out = velox().arg("export").arg(&decoded).args(["--to", to]).output().unwrap();
        assert!(out.status.success(), "{to}: {}", String::from_utf8_lossy(&out.stderr));
    }
    let export = decoded.join("export");
    let close = |a: &[f32], b: &[f32], tol: f32, what: &str| {
        assert_eq!(a.len(), b.len(), "{what}");
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() <= tol, "{what}: {x} -> {y}");
        }
    };
    for (k, f) in [0, 12].into_iter().enumerate() {
        // The PLY sequence: the frames' own bytes, under the names SuperSplat loads.
        let copied = export.join("ply-seq").join(frames::sequence_file(f, "ply"));
        assert_eq!(std::fs::read(copied).unwrap(), std::fs::read(source(f)).unwrap());
        // SPZ (version 3) and glTF: the same Gaussians, to their files' precision.
        let s = spz::read(&export.join("spz").join(frames::sequence_file(f, "spz"))).unwrap();
        close(&clip[k].means, &s.means, 1.0 / 8192.0 + 1e-6, "spz means");
        close(&clip[k].log_scales, &s.log_scales, 1.0 / 32.0 + 1e-6, "spz log scales");
        let glb_bytes = std::fs::read(export.join("glb").join(frames::sequence_file(f, "glb"))).unwrap();
        let (g, glb_sh) = glb::from_bytes_sh(&glb_bytes).unwrap();
        assert_eq!(g.means, clip[k].means);
        close(&clip[k].colours, &g.colours, 1e-6, "glb colours");
        let spz_bytes = std::fs::read(export.join("spz").join(frames::sequence_file(f, "spz"))).unwrap();
        let spz_sh = spz::from_bytes_sh(&spz_bytes).unwrap().1;
        if f == 12 {
            assert_eq!(glb_sh.as_ref(), Some(&sh), "glTF keeps the harmonics as they are");
            let spz_sh = spz_sh.expect("SPZ keeps the harmonics");
            close(&sh.coeffs, &spz_sh.coeffs, 16.0 / 256.0 + 1.0 / 256.0, "spz harmonics");
        } else {
            assert!(glb_sh.is_none() && spz_sh.is_none());
        }
    }
    // The flipbook: both frames in order, opening on the scene's first supervision camera.
    let book = splatv::read(&export.join("clip.splatv")).unwrap();
    assert_eq!(book.frames.len(), 2);
    assert_eq!(book.frames[1].means, clip[1].means);
    let cameras = velox_data::format::read_cameras(&scene).unwrap();
    assert_eq!(book.camera, SplatvCamera::of(&cameras.supervision[0], "supervision 0"));
    // --out names the place; SPZ version 2 on request; what cannot be exported is refused.
    let spz2 = decoded.join("v2");
    let out = velox()
        .arg("export")
        .arg(&decoded)
        .args(["--to", "spz", "--spz-version", "2", "--out"])
        .arg(&spz2)
        .output();
    assert!(out.unwrap().status.success());
    let bytes = std::fs::read(spz2.join("frame_0012.spz")).unwrap();
    assert_eq!(spz::from_bytes(&bytes).unwrap().len(), clip[1].len());
    let err = fails(velox().arg("export").arg(&scene).args(["--to", "glb"]));
    assert!(err.contains("holds no frames"), "{err}");
    let err = fails(velox().arg("export").arg(&decoded).args(["--to", "obj"]));
    assert!(err.contains("ply-seq"), "{err}");
    let _ = std::fs::remove_dir_all(decoded.parent().unwrap());
}

#[test]
fn a_mesh_sequence_opens_a_flat_gaussian_a_triangle() {
    // decode mesh's files: mesh_fFF.ply, a frame each, each triangle a flat Gaussian.
    let dir = temp_dir("meshes");
    let seq = dir.join("mesh");
    std::fs::create_dir_all(&seq).unwrap();
    for (f, n) in [(0usize, 4u32), (7, 5)] {
        let positions = (0..n).map(|i| [i as f32 * 0.1, (i % 2) as f32 * 0.1, 0.0]).collect();
        let triangles = (1..n - 1).map(|i| [0, i, i + 1]).collect();
        let m = velox_io::mesh::Mesh { positions, triangles };
        velox_io::mesh::write(&seq.join(frames::frame_file("mesh", f)), &m, velox_io::mesh::Format::Ply)
            .unwrap();
    }
    let page = dir.join("mesh.html");
    let out = velox().arg("view").arg(&seq).arg("--html").arg(&page).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stdout).contains("mesh triangles"));
    let text = std::fs::read_to_string(&page).unwrap();
    let manifest = manifest(&text);
    assert_eq!(manifest["kind"], "gaussians");
    assert_eq!(frame_counts(&manifest), [(0, 2), (7, 3)]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_track_output_of_a_long_clip_shows_every_frames_tracks() {
    // velox track over a capture imported in windows: 30 frames, the tracks over all of them.
    let dir = temp_dir("long-tracks");
    let out = dir.join("tracks");
    std::fs::create_dir_all(&out).unwrap();
    for f in 0..30 {
        let mut g = gaussians(2, f as u64);
        g.means[1] = f as f32 * 0.01;
        // Points as velox track writes them: x y z (the viewer takes any PLY of points).
        let mut ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n".to_vec();
        for v in &g.means {
            ply.extend_from_slice(&v.to_le_bytes());
        }
        std::fs::write(out.join(frames::frame_file("tracks", f)), ply).unwrap();
    }
    let query = |k: f32| velox_io::tracks::TrackedQuery {
        query: [k, 0.0, 0.0],
        positions: (0..30).map(|f| [k, f as f32 * 0.01, 0.0]).collect(),
        visible: vec![true; 30],
    };
    let report = velox_io::tracks::TrackReport {
        video: dir.join("video").display().to_string(),
        autoencoder: "ae.safetensors".into(),
        checkpoint: "tracker.safetensors".into(),
        frames: 30,
        source_frames: (0..30).collect(),
        queries: vec![query(0.1), query(0.2)],
    };
    report.write(&out).unwrap();
    let page = dir.join("tracks.html");
    let run = velox().arg("view").arg(&out).arg("--html").arg(&page).output().unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let m = manifest(&std::fs::read_to_string(&page).unwrap());
    assert_eq!(frame_counts(&m).len(), 30);
    assert_eq!((m["tracks"]["count"].as_u64(), m["tracks"]["frames"].as_u64()), (Some(2), Some(30)));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn higher_spherical_harmonics_are_drawn_along_each_view() {
    let (scene, decoded) = fixture("sh", 64, 0);
    let dir = decoded.parent().unwrap().to_path_buf();
    // Frame 12 with degree-3 harmonics strong enough to change its colours with the view.
    let path = decoded.join("gaussians_f12.ply");
    let g = ply::read(&path).unwrap();
    let k = ply::Sh::per_channel(3);
    let mut rng = Rng::new(5);
    let sh =
        ply::Sh { degree: 3, coeffs: (0..g.len() * 3 * k).map(|_| rng.range(-0.4, 0.4) as f32).collect() };
    std::fs::write(&path, ply::to_bytes_sh(&g, Some(&sh)).unwrap()).unwrap();
    // The colours scene camera 0 sees, baked into a PLY that velox render draws; and the
    // degree-0 colours alone.
    let eye = velox_tasks::view::scene_cameras(&scene).unwrap()[0].camera.centre();
    let mut baked = g.clone();
    for i in 0..g.len() {
        let d: [f64; 3] = std::array::from_fn(|a| (g.means[3 * i + a] - eye[a]) as f64);
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let base = [0, 1, 2].map(|c| g.colours[3 * i + c]);
        let c = ply::sh_colour(base, &sh.coeffs[i * 3 * k..(i + 1) * 3 * k], 3, d.map(|v| v / l));
        for (to, v) in baked.colours[3 * i..3 * i + 3].iter_mut().zip(c) {
            *to = v as f32;
        }
    }
    let (baked_dir, plain_dir) = (dir.join("baked"), dir.join("plain"));
    for (folder, gaussians) in [(&baked_dir, &baked), (&plain_dir, &g)] {
        std::fs::create_dir_all(folder).unwrap();
        ply::write(&folder.join("gaussians_f12.ply"), gaussians).unwrap();
    }
    let window = (64, 64);
    let server = serve(&decoded);
    let page = screenshot(
        &format!("http://{}/index.html#camera=0&frame=1&ui=0", server.address),
        window,
        &dir,
        "sh.png",
    );
    let (want, plain) =
        (rendered_f12(&baked_dir, &scene, &dir, window), rendered_f12(&plain_dir, &scene, &dir, window));
    let (p, without) = (psnr(&page, &want), psnr(&page, &plain));
    eprintln!(
        "page with SH against the baked render: PSNR {p:.1} dB; against degree 0 alone: {without:.1} dB"
    );
    assert!(p >= 30.0, "PSNR {p:.1} dB");
    assert!(without < p - 6.0, "the harmonics barely change the picture: {without:.1} dB without them");
    drop(server);
    let _ = std::fs::remove_dir_all(&dir);
}
