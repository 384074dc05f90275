//! A clip of per-frame Gaussians as one `.splatv` file, the format of splaTV's viewer
//! (antimatter15/splaTV) and gsplat.js: a flipbook, each frame's Gaussians visible in their
//! own stretch of the clip's time and still within it.
//!
//! The file: the u32 0x674b, the length of a JSON header (u32), the header (an array of one
//! chunk, `{"type": "splat", "size", "texwidth": 4096, "texheight", "cameras": [...]}`, the
//! cameras in the 3D Gaussian splatting layout: centre, camera-to-world rotation rows, focal
//! lengths, OpenCV axes as Velox's cameras), then the chunk: 16 little-endian u32 a Gaussian
//! (4 RGBA32UI texels; the texture holds 1024 a row, the last row padded):
//! - 0..2: the mean (f32); 3, 4: the quaternion (w, x), (y, z) as pairs of halves;
//! - 5, 6: the scales, linear, as halves (the sixth half zero);
//! - 7: the colour and opacity as RGBA8 (opacity = sigmoid(logit));
//! - 8..14: motion (velocity, acceleration, jerk and an angular velocity), all zero here;
//! - 15: the time centre c and width s (halves): the viewer scales the opacity at clip time
//!   t in [0, 1] by exp(-((t - c) / s)^2) and skips it below 0.02.
//!
//! Frame k of K gets c = (k + 1/2) / K and s = 1 / (2K): at a frame's centre time only it is
//! drawn (a neighbour has exp(-4) < 0.02 there), between two centres they cross-fade. The
//! viewers play t = 1/2 + sin(seconds) / 2, forward then back, every 6.3 s. The padding of the
//! last row is never visible (opacity 0, centre 1000).

use std::path::Path;

use half::f16;
use serde::{Deserialize, Serialize};
use velox_engine::ops::raster::{Camera, GaussianData};
use velox_engine::{Error, Result};

use crate::{read_parsed, write_bytes};

/// The file's first u32.
pub const MAGIC: u32 = 0x674b;
/// Texels in a row of the texture (4 a Gaussian).
const TEXWIDTH: usize = 4096;
/// Gaussians in a row.
const ROW: usize = TEXWIDTH / 4;
/// u32 words a Gaussian.
const WORDS: usize = 16;

fn bad(why: impl Into<String>) -> Error {
    Error::Invalid(why.into())
}

/// A camera in the header (3D Gaussian splatting's `cameras.json` layout).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SplatvCamera {
    pub id: usize,
    pub img_name: String,
    pub width: u32,
    pub height: u32,
    /// The camera's centre in the world.
    pub position: [f32; 3],
    /// Camera-to-world rotation, rows (camera x right, y down, z forward).
    pub rotation: [[f32; 3]; 3],
    pub fx: f32,
    pub fy: f32,
}

/// The image height a header camera's focal lengths are given for: the viewers apply them to
/// the browser window's pixels, so a camera of a 96-pixel image would open very wide.
pub const CAMERA_HEIGHT: u32 = 800;

impl SplatvCamera {
    /// Velox's camera (world-to-camera) in the header's layout, scaled to an image
    /// [`CAMERA_HEIGHT`] pixels tall (the same field of view).
    pub fn of(camera: &Camera, name: &str) -> SplatvCamera {
        let r = camera.rotation;
        let c2w = std::array::from_fn(|i| std::array::from_fn(|j| r[j][i]));
        let k = CAMERA_HEIGHT as f32 / camera.height as f32;
        SplatvCamera {
            id: 0,
            img_name: name.to_string(),
            width: (camera.width as f32 * k).round() as u32,
            height: CAMERA_HEIGHT,
            position: camera.centre(),
            rotation: c2w,
            fx: camera.fx * k,
            fy: camera.fy * k,
        }
    }
}

#[derive(Serialize, Deserialize)]
struct Chunk {
    #[serde(rename = "type")]
    kind: String,
    size: usize,
    texwidth: usize,
    texheight: usize,
    cameras: Vec<SplatvCamera>,
}

/// The time centre and width of frame `k` of `frames`.
pub fn frame_window(k: usize, frames: usize) -> (f32, f32) {
    ((k as f32 + 0.5) / frames as f32, 0.5 / frames as f32)
}

fn halves(a: f32, b: f32) -> u32 {
    f16::from_f32(a).to_bits() as u32 | (f16::from_f32(b).to_bits() as u32) << 16
}

fn unhalves(w: u32) -> [f32; 2] {
    [f16::from_bits(w as u16).to_f32(), f16::from_bits((w >> 16) as u16).to_f32()]
}

fn to_u8(x: f64) -> u32 {
    (x * 255.0).round().clamp(0.0, 255.0) as u32
}

/// The file's bytes for a clip of `frames` (in order) seen first from `camera`.
pub fn to_bytes(frames: &[GaussianData], camera: &SplatvCamera) -> Result<Vec<u8>> {
    if frames.is_empty() {
        return Err(bad("a .splatv clip needs at least one frame"));
    }
    let n: usize = frames.iter().map(|g| g.len()).sum();
    let texheight = n.div_ceil(ROW).max(1);
    let mut words = Vec::with_capacity(texheight * ROW * WORDS);
    for (k, g) in frames.iter().enumerate() {
        g.check()?;
        let (centre, width) = frame_window(k, frames.len());
        for i in 0..g.len() {
            let m = &g.means[3 * i..3 * i + 3];
            let q = &g.quats[4 * i..4 * i + 4];
            let s = &g.log_scales[3 * i..3 * i + 3];
            let c = &g.colours[3 * i..3 * i + 3];
            let l = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            if l.is_nan() || l <= 0.0 {
                return Err(bad(format!("frame {k}, Gaussian {i}: its quaternion is zero")));
            }
            let scale = s.iter().map(|v| v.exp()).collect::<Vec<_>>();
            if let Some(v) = scale.iter().find(|v| !(f16::from_f32(**v).is_finite())) {
                return Err(bad(format!("frame {k}, Gaussian {i}: scale {v} is past a half float's range")));
            }
            let opacity = 1.0 / (1.0 + (-g.opacities[i] as f64).exp());
            let rgba = to_u8(c[0] as f64)
                | to_u8(c[1] as f64) << 8
                | to_u8(c[2] as f64) << 16
                | to_u8(opacity) << 24;
            words.extend([m[0].to_bits(), m[1].to_bits(), m[2].to_bits()]);
            words.extend([halves(q[0] / l, q[1] / l), halves(q[2] / l, q[3] / l)]);
            words.extend([halves(scale[0], scale[1]), halves(scale[2], 0.0), rgba]);
            words.extend([0; 7]);
            words.push(halves(centre, width));
        }
    }
    // The padding: never visible.
    while words.len() < texheight * ROW * WORDS {
        words.extend([0; 15]);
        words.push(halves(1000.0, 0.001));
    }
    let chunk = Chunk {
        kind: "splat".into(),
        size: words.len() * 4,
        texwidth: TEXWIDTH,
        texheight,
        cameras: vec![camera.clone()],
    };
    let json = serde_json::to_vec(&[chunk]).map_err(|e| bad(e.to_string()))?;
    let mut out = Vec::with_capacity(8 + json.len() + words.len() * 4);
    out.extend_from_slice(&MAGIC.to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(&json);
    for w in words {
        out.extend_from_slice(&w.to_le_bytes());
    }
    Ok(out)
}

/// Writes a clip to `path` (atomically).
pub fn write(path: &Path, frames: &[GaussianData], camera: &SplatvCamera) -> Result<()> {
    write_bytes(path, &to_bytes(frames, camera)?)
}

/// A flipbook read back: its frames in time order (the Gaussians of each time centre) and its
/// first camera.
#[derive(Clone, Debug)]
pub struct Flipbook {
    pub frames: Vec<GaussianData>,
    pub camera: SplatvCamera,
}

/// Reads a flipbook from `path`.
pub fn read(path: &Path) -> Result<Flipbook> {
    read_parsed(path, from_bytes)
}

/// Parses a flipbook: Gaussians that move are refused (a splatv with motion is not a
/// flipbook), those whose time centre lies outside [0, 1] are padding and skipped.
pub fn from_bytes(bytes: &[u8]) -> Result<Flipbook> {
    let word = |at: usize| bytes.get(at..at + 4).map(|b| u32::from_le_bytes(b.try_into().unwrap()));
    if word(0) != Some(MAGIC) {
        return Err(bad("not a .splatv file: it does not start with 0x674b"));
    }
    let len = word(4).ok_or_else(|| bad("the file ends before its header's length"))? as usize;
    let json = bytes.get(8..8 + len).ok_or_else(|| bad("the file ends inside its JSON header"))?;
    let chunks: Vec<Chunk> =
        serde_json::from_slice(json).map_err(|e| bad(format!("the JSON header: {e}")))?;
    let chunk = chunks.first().ok_or_else(|| bad("the header lists no chunk"))?;
    let camera = chunk.cameras.first().cloned().ok_or_else(|| bad("the chunk has no camera"))?;
    if chunk.kind != "splat" || chunk.texwidth != TEXWIDTH {
        return Err(bad(format!(
            "a chunk of type {} and {} texels a row is not read",
            chunk.kind, chunk.texwidth
        )));
    }
    let body = &bytes[8 + len..];
    let gaussians = chunk.texheight * ROW;
    if chunk.size != gaussians * WORDS * 4 || body.len() < chunk.size {
        return Err(bad(format!(
            "the chunk's {} rows need {} bytes; its size says {}, the file holds {}",
            chunk.texheight,
            gaussians * WORDS * 4,
            chunk.size,
            body.len()
        )));
    }
    let mut frames: Vec<(f32, GaussianData)> = Vec::new();
    for i in 0..gaussians {
        let w: Vec<u32> = body[i * 64..(i + 1) * 64]
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        let [centre, _] = unhalves(w[15]);
        if !(0.0..=1.0).contains(&centre) {
            continue;
        }
        if w[8..15].iter().any(|&m| m & 0x7fff_7fff != 0) {
            return Err(bad(format!("Gaussian {i} moves: only still flipbook frames are read")));
        }
        let mean = [0, 1, 2].map(|k| f32::from_bits(w[k]));
        let [qw, qx] = unhalves(w[3]);
        let [qy, qz] = unhalves(w[4]);
        let [s0, s1] = unhalves(w[5]);
        let [s2, _] = unhalves(w[6]);
        let log_scale = [s0, s1, s2].map(|s| s.max(f32::MIN_POSITIVE).ln());
        let channel = |k: u32| ((w[7] >> (8 * k)) & 255) as f64 / 255.0;
        let a = channel(3).clamp(1.0 / 510.0, 1.0 - 1.0 / 510.0);
        let colour = [0, 1, 2].map(|k| channel(k) as f32);
        let at = match frames.iter().position(|(c, _)| *c == centre) {
            Some(at) => at,
            None => {
                frames.push((centre, GaussianData::default()));
                frames.len() - 1
            }
        };
        frames[at].1.push(mean, log_scale, [qw, qx, qy, qz], (a / (1.0 - a)).ln() as f32, colour);
    }
    frames.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(Flipbook { frames: frames.into_iter().map(|f| f.1).collect(), camera })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(n: usize, seed: u64) -> GaussianData {
        crate::test_gaussians(n, seed, 1.0, (-6.0, -1.0))
    }

    #[test]
    fn a_clip_round_trips_frame_by_frame() {
        // 1500 Gaussians over three frames: two texture rows, the second padded.
        let clip = [frame(700, 1), frame(300, 2), frame(500, 3)];
        let camera = Camera::look_at([0.0, 0.5, 3.0], [0.0; 3], [0.0, 1.0, 0.0], 50.0, 320, 240);
        let header = SplatvCamera::of(&camera, "supervision 0");
        let bytes = to_bytes(&clip, &header).unwrap();
        assert_eq!(
            bytes.len(),
            8 + u32::from_le_bytes(bytes[4..8].try_into().unwrap()) as usize + 2 * 1024 * 64
        );
        let back = from_bytes(&bytes).unwrap();
        assert_eq!(back.camera, header);
        // The camera's centre is the eye, its rotation the transpose of the world-to-camera one,
        // its field of view the same at 800 pixels.
        assert!(header.position.iter().zip([0.0, 0.5, 3.0]).all(|(a, b)| (a - b).abs() < 1e-5));
        assert_eq!(header.rotation[0][2], camera.rotation[2][0]);
        assert_eq!((header.width, header.height), (1067, 800));
        assert!((header.fy / 800.0 - camera.fy / 240.0).abs() < 1e-6);
        assert_eq!(back.frames.len(), 3);
        for (g, r) in clip.iter().zip(&back.frames) {
            assert_eq!(g.means, r.means, "positions are f32");
            for (a, b) in g.log_scales.iter().zip(&r.log_scales) {
                assert!((a - b).abs() < 1e-3, "log scale {a} -> {b}");
            }
            for (a, b) in g.colours.iter().zip(&r.colours) {
                assert!((a - b).abs() <= 0.5 / 255.0 + 1e-6, "colour {a} -> {b}");
            }
            let sigmoid = |x: f32| 1.0 / (1.0 + (-x).exp());
            for (a, b) in g.opacities.iter().zip(&r.opacities) {
                assert!((sigmoid(*a) - sigmoid(*b)).abs() <= 0.5 / 255.0 + 1e-5, "opacity {a} -> {b}");
            }
            for (a, b) in g.quats.chunks(4).zip(r.quats.chunks(4)) {
                let l = a.iter().map(|v| v * v).sum::<f32>().sqrt();
                assert!(a.iter().zip(b).all(|(x, y)| (x / l - y).abs() < 1e-3), "{a:?} -> {b:?}");
            }
        }
    }

    #[test]
    fn each_frame_owns_its_centre_time() {
        let k = 24;
        for f in 0..k {
            let (c, s) = frame_window(f, k);
            let visibility = |t: f32| (-((t - c) / s).powi(2)).exp();
            assert_eq!(visibility(c), 1.0);
            for other in [f.wrapping_sub(1), f + 1].into_iter().filter(|&o| o < k) {
                assert!(
                    visibility(frame_window(other, k).0) < 0.02,
                    "frame {f} is culled at frame {other}'s time"
                );
            }
        }
    }

    #[test]
    fn bad_files_are_named() {
        let e = |b: &[u8]| from_bytes(b).unwrap_err().to_string();
        assert!(e(b"ply\n").contains("not a .splatv"));
        let camera = SplatvCamera::of(&Camera::identity(50.0, 64, 64), "c");
        let bytes = to_bytes(&[frame(10, 1)], &camera).unwrap();
        assert!(e(&bytes[..bytes.len() - 4]).contains("need"));
        let mut moving = bytes.clone();
        let body = moving.len() - 1024 * 64;
        moving[body + 8 * 4] = 1;
        assert!(e(&moving).contains("Gaussian 0 moves"));
        assert!(to_bytes(&[], &camera).unwrap_err().to_string().contains("at least one frame"));
    }
}
