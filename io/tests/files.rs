//! The files users see, written and read back: Gaussians as PLY (the 3D Gaussian splatting
//! layout and the others readers meet), PNG images and EXR depth; malformed files are errors
//! that name the problem.

#[path = "../../engine/tests/common/mod.rs"]
mod common;

use common::random_gaussians;
use velox_engine::rng::Rng;
use velox_io::{image, ply};

fn temp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("velox-raster-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

#[test]
fn ply_round_trip_and_layout() {
    let g = random_gaussians(57, 81, (-3.0, -1.0), (-2.0, 2.0));
    let path = temp("round.ply");
    ply::write(&path, &g).unwrap();
    let back = ply::read(&path).unwrap();
    assert_eq!(back.means, g.means);
    assert_eq!(back.log_scales, g.log_scales);
    assert_eq!(back.quats, g.quats);
    assert_eq!(back.opacities, g.opacities);
    for (a, b) in back.colours.iter().zip(&g.colours) {
        assert!((a - b).abs() < 1e-6, "colour {a} vs {b}");
    }
    let bytes = std::fs::read(&path).unwrap();
    let header = String::from_utf8_lossy(&bytes[..600]);
    assert!(header.starts_with("ply\nformat binary_little_endian 1.0\nelement vertex 57\nproperty float x\n"));
    assert!(
        header.contains("property float f_dc_0\n") && header.contains("property float rot_3\nend_header\n")
    );
}

/// A file as other tools write it: doubles, extra properties in another order, higher
/// spherical harmonics, another element before the vertices.
#[test]
fn ply_reads_other_layouts() {
    let names = [
        "rot_0", "rot_1", "rot_2", "rot_3", "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "f_rest_0",
        "opacity", "scale_0", "scale_1", "scale_2",
    ];
    let mut bytes = b"ply\nformat binary_little_endian 1.0\ncomment made by hand\nelement camera 1\nproperty uchar id\nelement vertex 2\n".to_vec();
    for n in names {
        bytes.extend_from_slice(format!("property double {n}\n").as_bytes());
    }
    bytes.extend_from_slice(b"end_header\n");
    bytes.push(7); // the camera element
    for i in 0..2 {
        let v = [1.0, 0.0, 0.0, 0.0, 0.5 + i as f64, -1.0, 3.0, 0.0, 1.0, -1.0, 9.0, 2.0, -4.0, -4.5, -5.0];
        for x in v {
            bytes.extend_from_slice(&f64::to_le_bytes(x));
        }
    }
    let g = ply::from_bytes(&bytes).unwrap();
    assert_eq!(g.len(), 2);
    assert_eq!(&g.means[3..], &[1.5, -1.0, 3.0]);
    assert_eq!(&g.quats[..4], &[1.0, 0.0, 0.0, 0.0]);
    assert_eq!(&g.log_scales[..3], &[-4.0, -4.5, -5.0]);
    assert_eq!(g.opacities, vec![2.0, 2.0]);
    assert!((g.colours[1] - (0.5 + ply::SH_C0 as f32)).abs() < 1e-7);
}

#[test]
fn malformed_ply_files_are_clear_errors() {
    let good = ply::to_bytes(&random_gaussians(3, 91, (-3.0, -1.0), (0.0, 1.0))).unwrap();
    let expect = |bytes: &[u8], needle: &str| {
        let e = ply::from_bytes(bytes).unwrap_err().to_string();
        assert!(e.contains(needle), "error `{e}` should mention `{needle}`");
    };
    expect(&good[..good.len() - 5], "truncated");
    expect(b"hello", "not a PLY file");
    expect(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n", "ascii");
    expect(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n", "`y`");
    expect(
        b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list uchar int v\nend_header\n",
        "no `vertex` element",
    );
    expect(b"ply\nformat binary_little_endian 1.0\nelement vertex many\nend_header\n", "not a number");
    assert!(ply::read(&temp("missing.ply")).unwrap_err().to_string().contains("missing.ply"));
}

/// A file that fails is an error that holds its path and what was done with it: reading it,
/// understanding it, or writing it.
#[test]
fn file_errors_name_the_file_and_what_failed() {
    use velox_engine::{Error, FileOp};
    let op_of = |e: Error, want: &std::path::Path| match e {
        Error::File { path, op, reason } => {
            assert_eq!(path, want);
            assert!(!reason.is_empty());
            op
        }
        other => panic!("not a file error: {other:?}"),
    };
    let missing = temp("absent.ply");
    assert_eq!(op_of(ply::read(&missing).unwrap_err(), &missing), FileOp::Read);
    let garbage = temp("garbage.ply");
    std::fs::write(&garbage, b"hello").unwrap();
    assert_eq!(op_of(ply::read(&garbage).unwrap_err(), &garbage), FileOp::Content);
    let png = temp("garbage.png");
    std::fs::write(&png, b"not a png").unwrap();
    assert_eq!(op_of(image::read_png(&png).unwrap_err(), &png), FileOp::Content);
    let nowhere = temp("no-such-folder").join("out.ply");
    let g = random_gaussians(2, 5, (-3.0, -1.0), (0.0, 1.0));
    assert_eq!(op_of(ply::write(&nowhere, &g).unwrap_err(), &nowhere), FileOp::Write);
}

/// The body holds exactly what the header declares, counts that overflow any file are
/// errors, and every value read is finite.
#[test]
fn ply_body_must_match_its_header_and_hold_finite_values() {
    let good = ply::to_bytes(&random_gaussians(3, 92, (-3.0, -1.0), (0.0, 1.0))).unwrap();
    let text = String::from_utf8_lossy(&good[..good.len() - 3 * 17 * 4]).into_owned();
    let body = &good[text.len()..];
    let expect = |bytes: &[u8], needles: &[&str]| {
        let e = ply::from_bytes(bytes).unwrap_err().to_string();
        assert!(needles.iter().all(|n| e.contains(n)), "error `{e}` should mention {needles:?}");
    };
    // A header that says uchar over a body of floats.
    let uchar = text.replace("property float", "property uchar");
    expect(&[uchar.as_bytes(), body].concat(), &["does not match the header", "3 vertex of 17 bytes"]);
    // Trailing bytes after the declared vertices.
    expect(&[&good[..], b"\0\0\0\0"].concat(), &["does not match the header", "204 bytes", "has 208"]);
    // A count no file can hold, in the vertices and in an element before them.
    let huge = text.replace("element vertex 3", "element vertex 1000000000000000000");
    expect(&[huge.as_bytes(), body].concat(), &["truncated", "1000000000000000000 vertex"]);
    let before = text
        .replace("element vertex", "element camera 18446744073709551615\nproperty double id\nelement vertex");
    expect(&[before.as_bytes(), body].concat(), &["truncated", "18446744073709551615 camera of 8 bytes"]);
    // NaN and Inf in a value the reader keeps; a double beyond f32.
    for (k, bits) in [(9usize, f32::NAN), (0, f32::INFINITY)] {
        let mut bad = good.clone();
        let at = text.len() + 17 * 4 + 4 * k;
        bad[at..at + 4].copy_from_slice(&bits.to_le_bytes());
        let name = ["x", "", "", "", "", "", "", "", "", "opacity"][k];
        expect(&bad, &["vertex 1", &format!("{name} is")]);
    }
    let mut double = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n".to_vec();
    let names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2"];
    for n in names.iter().chain(&["rot_0", "rot_1", "rot_2", "rot_3"]) {
        double.extend_from_slice(format!("property double {n}\n").as_bytes());
    }
    double.extend_from_slice(b"end_header\n");
    for v in [1e300, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -3.0, -3.0, -3.0, 1.0, 0.0, 0.0, 0.0] {
        double.extend_from_slice(&f64::to_le_bytes(v));
    }
    expect(&double, &["vertex 0", "x is 1e300"]);
}

#[test]
fn png_and_exr_round_trip() {
    let (w, h) = (13u32, 7u32);
    let mut rng = Rng::new(101);
    let rgb = rng.uniform_vec((w * h * 3) as usize, -0.2, 1.2);
    let path = temp("img.png");
    image::write_png(&path, &rgb, w, h).unwrap();
    let (back, bw, bh) = image::read_png(&path).unwrap();
    assert_eq!((bw, bh), (w, h));
    for (a, b) in back.iter().zip(&rgb) {
        assert!((a - b.clamp(0.0, 1.0)).abs() <= 0.5 / 255.0 + 1e-6);
    }
    let depth = rng.uniform_vec((w * h) as usize, 0.0, 10.0);
    let path = temp("depth.exr");
    image::write_exr_depth(&path, &depth, w, h).unwrap();
    let (back, bw, bh) = image::read_exr_depth(&path).unwrap();
    assert_eq!((bw, bh, back), (w, h, depth));
    assert!(image::write_png(&path, &rgb[1..], w, h).is_err(), "wrong length");
    assert!(image::read_exr_depth(&temp("img.png")).is_err());
}

#[test]
fn gif_frames_round_trip_within_their_palette() {
    let (w, h) = (17u32, 9u32);
    let n = (w * h * 3) as usize;
    // A few flat colours (exact in any palette) and a smooth ramp (quantised).
    let flat: Vec<f32> = (0..n).map(|i| [0.0, 1.0, 0.2][(i / 3 / w as usize) % 3]).collect();
    let ramp: Vec<f32> = (0..n).map(|i| (i % (3 * w as usize)) as f32 / (3 * w) as f32).collect();
    let path = temp("seq.gif");
    image::write_gif(&path, &[flat.clone(), ramp.clone(), flat.clone()], w, h, 95).unwrap();
    let image::Gif { frames, width: bw, height: bh, delays_ms: delays } = image::read_gif(&path).unwrap();
    assert_eq!((frames.len(), bw, bh), (3, w, h));
    assert_eq!(delays, vec![100; 3], "95 ms rounds up to GIF's 10 ms steps");
    let worst = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
    assert!(worst(&frames[0], &flat) <= 0.5 / 255.0 + 1e-6);
    assert!(worst(&frames[1], &ramp) <= 8.0 / 255.0, "{}", worst(&frames[1], &ramp));
    assert!(image::write_gif(&path, &[], w, h, 100).is_err(), "no frames");
    assert!(image::write_gif(&path, &[flat[1..].to_vec()], w, h, 100).is_err(), "wrong length");
}

#[test]
fn higher_spherical_harmonics_pass_through_and_evaluate_as_3dgs_does() {
    let g = random_gaussians(5, 17, (-3.0, -1.0), (0.0, 1.0));
    for degree in 1..=3 {
        let k = ply::Sh::per_channel(degree);
        let coeffs: Vec<f32> = (0..5 * 3 * k).map(|i| (i as f32 * 0.37).sin() * 0.3).collect();
        let sh = ply::Sh { degree, coeffs };
        let bytes = ply::to_bytes_sh(&g, Some(&sh)).unwrap();
        let (back, back_sh) = ply::from_bytes_sh(&bytes).unwrap();
        assert_eq!(back_sh.as_ref(), Some(&sh), "degree {degree}");
        assert_eq!(back, ply::from_bytes(&bytes).unwrap(), "the plain reader takes the same Gaussians");
        let text =
            String::from_utf8_lossy(&bytes[..bytes.windows(10).position(|w| w == b"end_header").unwrap()])
                .to_string();
        let names: Vec<&str> = text.lines().filter_map(|l| l.strip_prefix("property float ")).collect();
        assert_eq!(names[9], "f_rest_0", "after f_dc_2, as 3D Gaussian splatting writes them");
        assert_eq!(names[9 + 3 * k], "opacity");
    }
    assert_eq!(ply::from_bytes_sh(&ply::to_bytes(&g).unwrap()).unwrap().1, None);
    // Degree 1 along +y is -C1 times the first coefficient of each channel; along +x the third.
    let c1 = 0.4886025119029199;
    let rest = [0.2, 0.0, 0.1, /* green */ -0.3, 0.0, 0.0, /* blue */ 0.0, 0.5, 0.0];
    let up = ply::sh_colour([0.5; 3], &rest, 1, [0.0, 1.0, 0.0]);
    let want = [0.5 - c1 * 0.2, 0.5 + c1 * 0.3, 0.5];
    assert!(up.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-7), "{up:?}");
    let right = ply::sh_colour([0.5; 3], &rest, 1, [1.0, 0.0, 0.0]);
    assert!((right[0] - (0.5 - c1 * 0.1)).abs() < 1e-7 && right[2] == 0.5, "{right:?}");
    // Clamped below at 0.
    assert_eq!(ply::sh_colour([0.0; 3], &[-1.0; 9], 1, [0.0, 0.0, 1.0])[1], 0.0);
    // A count that is no degree is refused.
    let mut odd = ply::to_bytes_sh(&g, Some(&ply::Sh { degree: 1, coeffs: vec![0.0; 45] })).unwrap();
    let at = odd.windows(9).position(|w| w == b"f_rest_8\n").unwrap();
    odd.splice(at..at + 9, b"f_rest_9\n".iter().copied());
    assert!(ply::from_bytes_sh(&odd).unwrap_err().to_string().contains("f_rest_8 is missing"));
}
