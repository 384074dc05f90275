//! Gaussians as SPZ, the compressed splat format Niantic published (nianticlabs/spz): a gzip
//! stream holding a 16-byte header and one block per quantity, 64 bytes a Gaussian cut to
//! about 16 before compression.
//!
//! The header, all little-endian: magic `NGSP` (u32 0x5053474e), version (u32: 2 or 3 are
//! written, 2 and 3 read), the Gaussian count (u32), the spherical-harmonic degree (u8: 0 here,
//! the colour alone), fractional bits of the positions (u8: 12), flags (u8: 0) and a reserved
//! byte. Then, for all Gaussians at once, each quantity in turn:
//! - positions: 3 x 24-bit two's complement fixed point (1/4096 units: a resolution of 0.24 mm
//!   in a scene measured in metres, a range of +-2048);
//! - opacity: sigmoid(logit) x 255, rounded;
//! - colour: the degree-0 coefficient f_dc (colour = 0.5 + C0 f_dc) as f_dc x 0.15 x 255 + 127.5;
//! - scales: (ln s + 10) x 16, ln s in [-10, 5.94] in steps of 1/16;
//! - rotation, the unit quaternion (x, y, z, w): version 2 keeps x, y, z of the one with w >= 0
//!   as q x 127.5 + 127.5; version 3 keeps the three smallest components in 10 bits each (sign
//!   and 9 bits of |q| / sqrt(1/2)) and the largest one's index in the top 2 bits of a u32.
//!
//! SPZ stores its positions right, up, back; Velox's world is y up and right-handed, so the
//! coordinates are written as they are. Values quantise as above; [`from_bytes`] reads them
//! back to within those steps, and opacities of 0 or 255 to the logit of 1/510 below 1 or
//! above 0 (the file cannot say more, and a logit must be finite).

use std::io::{Read, Write};
use std::path::Path;

use flate2::read::GzDecoder;
use flate2::write::GzEncoder;
use flate2::Compression;
use velox_engine::ops::raster::GaussianData;
use velox_engine::{Error, Result};

use crate::ply::{Sh, SH_C0};
use crate::{read_parsed, write_bytes};

/// `NGSP`, read as a little-endian u32.
pub const MAGIC: u32 = 0x5053_474e;
/// Fractional bits of the positions' fixed point.
pub const FRACTIONAL_BITS: u8 = 12;
/// f_dc's scale in the colour bytes.
const COLOUR_SCALE: f64 = 0.15;
const SQRT1_2: f64 = std::f64::consts::FRAC_1_SQRT_2;

fn bad(why: impl Into<String>) -> Error {
    Error::Invalid(why.into())
}

fn to_u8(x: f64) -> u8 {
    x.round().clamp(0.0, 255.0) as u8
}

/// The unit quaternion (x, y, z, w) of Velox's (w, x, y, z), of any length but zero.
fn unit_xyzw(q: &[f32]) -> [f64; 4] {
    let [w, x, y, z] = [q[0], q[1], q[2], q[3]].map(f64::from);
    let l = (w * w + x * x + y * y + z * z).sqrt();
    [x / l, y / l, z / l, w / l]
}

/// Quaternion (x, y, z, w) as version 3 packs it: the largest component dropped (the others
/// taken from the quaternion or its negation that makes it positive), its index on top.
fn pack_smallest_three(q: [f64; 4]) -> u32 {
    let mut largest = 0;
    for i in 1..4 {
        if q[i].abs() > q[largest].abs() {
            largest = i;
        }
    }
    let negate = q[largest] < 0.0;
    let mut packed = largest as u32;
    for (i, &v) in q.iter().enumerate() {
        if i == largest {
            continue;
        }
        let sign = ((v < 0.0) != negate) as u32;
        let magnitude = ((511.0 * v.abs() / SQRT1_2 + 0.5) as u32).min(511);
        packed = (packed << 10) | (sign << 9) | magnitude;
    }
    packed
}

fn unpack_smallest_three(mut packed: u32) -> [f64; 4] {
    let largest = (packed >> 30) as usize;
    let mut q = [0.0; 4];
    let mut sum = 0.0;
    for i in (0..4).rev() {
        if i == largest {
            continue;
        }
        let magnitude = (packed & 511) as f64;
        let negative = (packed >> 9) & 1 == 1;
        packed >>= 10;
        let v = SQRT1_2 * magnitude / 511.0;
        q[i] = if negative { -v } else { v };
        sum += v * v;
    }
    q[largest] = (1.0 - sum).max(0.0).sqrt();
    q
}

/// The file's bytes for `g` in SPZ `version` 2 or 3. Positions must lie within +-2048 (the
/// fixed point's range); every quaternion must have a length.
pub fn to_bytes(g: &GaussianData, version: u32) -> Result<Vec<u8>> {
    to_bytes_sh(g, None, version)
}

/// One higher spherical-harmonic coefficient as SPZ stores it: x 128 + 128, in steps of
/// `bucket` (8 for degree 1, 16 above: 5 and 4 bits, as the reference writer keeps them).
fn sh_byte(x: f32, bucket: i32) -> u8 {
    let q = (x as f64 * 128.0).round() as i32 + 128;
    ((q + bucket / 2) / bucket * bucket).clamp(0, 255) as u8
}

/// [`to_bytes`] with the Gaussians' higher spherical harmonics (degree 1 to 3), each
/// coefficient's three channels together as SPZ orders them.
pub fn to_bytes_sh(g: &GaussianData, sh: Option<&Sh>, version: u32) -> Result<Vec<u8>> {
    g.check()?;
    if let Some(sh) = sh.filter(|sh| sh.coeffs.len() != g.len() * sh.stride()) {
        return Err(Error::Shape(format!(
            "spherical harmonics: {} coefficients for {} Gaussians",
            sh.coeffs.len(),
            g.len()
        )));
    }
    if !(2..=3).contains(&version) {
        return Err(bad(format!("SPZ version {version} is not written: 2 or 3")));
    }
    let n = g.len();
    let count = u32::try_from(n)
        .ok()
        .filter(|&c| c <= i32::MAX as u32)
        .ok_or_else(|| bad(format!("{n} Gaussians are more than an SPZ file holds ({})", i32::MAX)))?;
    let scale = (1u32 << FRACTIONAL_BITS) as f64;
    let limit = (1i32 << 23) as f64 / scale;
    let rotation_bytes = if version == 2 { 3 } else { 4 };
    let mut raw = Vec::with_capacity(16 + n * (9 + 1 + 3 + 3 + rotation_bytes));
    raw.extend_from_slice(&MAGIC.to_le_bytes());
    raw.extend_from_slice(&version.to_le_bytes());
    raw.extend_from_slice(&count.to_le_bytes());
    raw.extend_from_slice(&[sh.map_or(0, |sh| sh.degree as u8), FRACTIONAL_BITS, 0, 0]);
    for (i, &p) in g.means.iter().enumerate() {
        let p = p as f64;
        if p.is_nan() || p.abs() >= limit {
            return Err(bad(format!(
                "Gaussian {}: coordinate {p} is outside the +-{limit} SPZ's positions hold",
                i / 3
            )));
        }
        let fixed = (p * scale).round() as i32;
        raw.extend_from_slice(&fixed.to_le_bytes()[..3]);
    }
    raw.extend(g.opacities.iter().map(|&o| to_u8(255.0 / (1.0 + (-o as f64).exp()))));
    raw.extend(g.colours.iter().map(|&c| {
        let dc = (c as f64 - 0.5) / SH_C0;
        to_u8(dc * COLOUR_SCALE * 255.0 + 127.5)
    }));
    raw.extend(g.log_scales.iter().map(|&s| to_u8((s as f64 + 10.0) * 16.0)));
    for (i, q) in g.quats.chunks_exact(4).enumerate() {
        if q.iter().all(|&v| v == 0.0) {
            return Err(bad(format!("Gaussian {i}: its quaternion is zero")));
        }
        let q = unit_xyzw(q);
        if version == 2 {
            let k = if q[3] < 0.0 { -127.5 } else { 127.5 };
            raw.extend(q[..3].iter().map(|&v| to_u8(v * k + 127.5)));
        } else {
            raw.extend_from_slice(&pack_smallest_three(q).to_le_bytes());
        }
    }
    if let Some(sh) = sh {
        let k = Sh::per_channel(sh.degree);
        for rest in sh.coeffs.chunks_exact(3 * k) {
            for j in 0..k {
                let bucket = if j < 3 { 8 } else { 16 };
                raw.extend((0..3).map(|c| sh_byte(rest[c * k + j], bucket)));
            }
        }
    }
    let mut gz = GzEncoder::new(Vec::new(), Compression::default());
    gz.write_all(&raw).and_then(|_| gz.finish()).map_err(|e| bad(format!("compressing: {e}")))
}

/// Writes `g` to `path` (atomically) as SPZ `version`.
pub fn write(path: &Path, g: &GaussianData, version: u32) -> Result<()> {
    write_bytes(path, &to_bytes(g, version)?)
}

/// Reads Gaussians from an SPZ file.
pub fn read(path: &Path) -> Result<GaussianData> {
    read_parsed(path, from_bytes)
}

/// Parses an SPZ file's bytes (versions 2 and 3, any spherical-harmonic degree: the degrees
/// above 0 are skipped, as the PLY reader skips them).
pub fn from_bytes(bytes: &[u8]) -> Result<GaussianData> {
    Ok(from_bytes_sh(bytes)?.0)
}

/// [`from_bytes`] with the higher spherical harmonics (degrees 1 to 3; degree 4 is refused),
/// in the PLY's order, each coefficient (byte - 128) / 128.
pub fn from_bytes_sh(bytes: &[u8]) -> Result<(GaussianData, Option<Sh>)> {
    if bytes.starts_with(&MAGIC.to_le_bytes()) {
        return Err(bad("an SPZ file of version 4 (zstd streams) is not read: versions 2 and 3 (gzip) are"));
    }
    if !bytes.starts_with(&[0x1f, 0x8b]) {
        return Err(bad("not an SPZ file: it is not a gzip stream"));
    }
    let mut raw = Vec::new();
    GzDecoder::new(bytes)
        .read_to_end(&mut raw)
        .map_err(|e| bad(format!("the gzip stream is broken: {e}")))?;
    if raw.len() < 16 {
        return Err(bad(format!("the SPZ header needs 16 bytes, the stream holds {}", raw.len())));
    }
    let word = |at: usize| u32::from_le_bytes(raw[at..at + 4].try_into().unwrap());
    if word(0) != MAGIC {
        return Err(bad(format!(
            "not an SPZ stream: magic {:#010x}, expected {MAGIC:#010x} (NGSP)",
            word(0)
        )));
    }
    let version = word(4);
    if !(2..=3).contains(&version) {
        return Err(bad(format!("SPZ version {version} is not read: 2 and 3 are")));
    }
    let n = word(8) as usize;
    let (degree, fractional) = (raw[12], raw[13]);
    if degree > 4 {
        return Err(bad(format!("spherical-harmonic degree {degree}: SPZ holds 0 to 4")));
    }
    if fractional > 23 {
        return Err(bad(format!("{fractional} fractional bits in 24-bit positions")));
    }
    if raw[14] & 2 != 0 {
        return Err(bad("the file holds SPZ extensions, which are not read"));
    }
    let sh = [0, 3, 8, 15, 24][degree as usize] * 3;
    let rotation_bytes = if version == 2 { 3 } else { 4 };
    let stride = 9 + 1 + 3 + 3 + rotation_bytes + sh;
    let need = 16u128 + n as u128 * stride as u128;
    if raw.len() as u128 != need {
        return Err(bad(format!(
            "{n} Gaussians of degree {degree} need {need} bytes after decompression, the stream holds {}",
            raw.len()
        )));
    }
    let mut at = 16;
    let mut block = |len: usize| {
        let b = &raw[at..at + len];
        at += len;
        b
    };
    let (positions, alphas, colours, scales, rotations) =
        (block(9 * n), block(n), block(3 * n), block(3 * n), block(rotation_bytes * n));
    let sh_bytes = block(sh * n);
    let scale = (1u32 << fractional) as f64;
    let mut g = GaussianData::default();
    for i in 0..n {
        let mean = std::array::from_fn(|k| {
            let b = &positions[9 * i + 3 * k..9 * i + 3 * k + 3];
            // Sign-extended from 24 bits.
            let fixed = i32::from_le_bytes([0, b[0], b[1], b[2]]) >> 8;
            (fixed as f64 / scale) as f32
        });
        let a = (alphas[i] as f64 / 255.0).clamp(1.0 / 510.0, 1.0 - 1.0 / 510.0);
        let logit = (a / (1.0 - a)).ln() as f32;
        let colour = std::array::from_fn(|k| {
            (0.5 + SH_C0 * (colours[3 * i + k] as f64 / 255.0 - 0.5) / COLOUR_SCALE) as f32
        });
        let log_scale = std::array::from_fn(|k| (scales[3 * i + k] as f64 / 16.0 - 10.0) as f32);
        let [x, y, z, w] = if version == 2 {
            let r = &rotations[3 * i..3 * i + 3];
            let v = [0, 1, 2].map(|k| r[k] as f64 / 127.5 - 1.0);
            let w = (1.0 - v.iter().map(|x| x * x).sum::<f64>()).max(0.0).sqrt();
            [v[0], v[1], v[2], w]
        } else {
            unpack_smallest_three(u32::from_le_bytes(rotations[4 * i..4 * i + 4].try_into().unwrap()))
        };
        g.push(mean, log_scale, [w, x, y, z].map(|v| v as f32), logit, colour);
    }
    let sh = match degree {
        0 => None,
        4 => return Err(bad("spherical harmonics of degree 4 are not read: 0 to 3 are")),
        d => {
            let k = Sh::per_channel(d as usize);
            let mut coeffs = vec![0.0f32; n * 3 * k];
            for (i, b) in sh_bytes.iter().enumerate() {
                let (point, j, c) = (i / (3 * k), (i / 3) % k, i % 3);
                coeffs[point * 3 * k + c * k + j] = (*b as f32 - 128.0) / 128.0;
            }
            Some(Sh { degree: d as usize, coeffs })
        }
    };
    Ok((g, sh))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(n: usize, seed: u64) -> GaussianData {
        crate::test_gaussians(n, seed, 3.0, (-6.0, 1.0))
    }

    fn sigmoid(x: f32) -> f64 {
        1.0 / (1.0 + (-x as f64).exp())
    }

    /// The angle between two rotations (radians), whatever their lengths and signs.
    fn angle(a: &[f32], b: &[f32]) -> f64 {
        let (a, b) = (unit_xyzw(a), unit_xyzw(b));
        let dot: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
        2.0 * dot.abs().min(1.0).acos()
    }

    #[test]
    fn gaussians_round_trip_within_the_quantisation() {
        let g = scene(500, 9);
        for version in [2, 3] {
            let bytes = to_bytes(&g, version).unwrap();
            assert_eq!(&bytes[..2], &[0x1f, 0x8b], "a gzip stream");
            let r = from_bytes(&bytes).unwrap();
            assert_eq!(r.len(), g.len());
            for (a, b) in g.means.iter().zip(&r.means) {
                assert!((a - b).abs() <= 0.5 / 4096.0 + 1e-6, "position {a} -> {b}");
            }
            for (a, b) in g.log_scales.iter().zip(&r.log_scales) {
                assert!((a - b).abs() <= 1.0 / 32.0 + 1e-6, "log scale {a} -> {b}");
            }
            for (a, b) in g.opacities.iter().zip(&r.opacities) {
                assert!((sigmoid(*a) - sigmoid(*b)).abs() <= 0.5 / 255.0 + 1e-6, "opacity {a} -> {b}");
            }
            // One colour step is 1 / (0.15 x 255) of f_dc, C0 / 38.25 of colour.
            for (a, b) in g.colours.iter().zip(&r.colours) {
                assert!(((a - b).abs() as f64) <= 0.5 * SH_C0 / 38.25 + 1e-6, "colour {a} -> {b}");
            }
            for (a, b) in g.quats.chunks(4).zip(r.quats.chunks(4)) {
                if version == 2 {
                    // x, y, z of the quaternion with w >= 0 to half a step of 1 / 127.5; w made
                    // from them, so its square is off by what theirs is: near w = 0 a rotation
                    // can be off by a tenth of a radian, why version 3 is the default.
                    let q = unit_xyzw(a);
                    let q = if q[3] < 0.0 { q.map(|v| -v) } else { q };
                    let step = 0.5 / 127.5 + 1e-6;
                    for k in 0..3 {
                        assert!((q[k] - b[k + 1] as f64).abs() <= step, "{a:?} -> {b:?}");
                    }
                    let w2 = 2.0 * 3f64.sqrt() * step + 3.0 * step * step;
                    assert!((q[3] - b[0] as f64).abs() <= w2.sqrt(), "{a:?} -> {b:?}");
                } else {
                    // Nine bits of the three smallest components: within 0.006 rad.
                    assert!(angle(a, b) < 0.006, "{a:?} -> {b:?}, {} rad", angle(a, b));
                }
            }
        }
    }

    #[test]
    fn spherical_harmonics_round_trip_in_spz_order() {
        let g = scene(50, 3);
        for degree in 1..=3 {
            let k = Sh::per_channel(degree);
            let coeffs: Vec<f32> = (0..50 * 3 * k).map(|i| ((i * 7919) % 200) as f32 / 100.0 - 1.0).collect();
            let sh = Sh { degree, coeffs };
            let (back, back_sh) = from_bytes_sh(&to_bytes_sh(&g, Some(&sh), 3).unwrap()).unwrap();
            assert_eq!(back, from_bytes(&to_bytes(&g, 3).unwrap()).unwrap(), "the rest is the same");
            let back_sh = back_sh.unwrap();
            assert_eq!(back_sh.degree, degree);
            // Degree 1 in steps of 8/128, the rest of 16/128, after a first rounding to 1/128:
            // within half a step and half of 1/128 (or clamped at 127/128).
            for (i, (a, b)) in sh.coeffs.iter().zip(&back_sh.coeffs).enumerate() {
                let step = if i % k < 3 { 8.0 } else { 16.0 } / 128.0;
                let bound = step / 2.0 + 0.5 / 128.0 + 1e-6;
                assert!((a - b).abs() <= bound || (*a > 0.99 && *b >= 0.99 - step), "{i}: {a} -> {b}");
            }
        }
        // The bytes: coefficient 0's red, green, blue, then coefficient 1's.
        let mut one = GaussianData::default();
        one.push([0.0; 3], [0.0; 3], [1.0, 0.0, 0.0, 0.0], 0.0, [0.5; 3]);
        let rest = [0.5, 0.0, 0.0, /* green */ -0.5, 0.0, 0.0, /* blue */ 0.25, 0.0, 0.0];
        let mut raw = Vec::new();
        GzDecoder::new(&to_bytes_sh(&one, Some(&Sh { degree: 1, coeffs: rest.to_vec() }), 3).unwrap()[..])
            .read_to_end(&mut raw)
            .unwrap();
        assert_eq!(raw[12], 1, "the degree");
        assert_eq!(&raw[raw.len() - 9..], &[192, 64, 160, 128, 128, 128, 128, 128, 128]);
    }

    #[test]
    fn the_layout_is_the_published_one() {
        // One Gaussian with known bytes: position (1, -1, 0.5), opacity 0, log scale -10 and
        // 5.9375, colour f_dc 0, the identity rotation.
        let mut g = GaussianData::default();
        g.push([1.0, -1.0, 0.5], [-10.0, 5.9375, 0.0], [1.0, 0.0, 0.0, 0.0], 0.0, [0.5; 3]);
        let mut raw = Vec::new();
        GzDecoder::new(&to_bytes(&g, 2).unwrap()[..]).read_to_end(&mut raw).unwrap();
        let header = [b'N', b'G', b'S', b'P', 2, 0, 0, 0, 1, 0, 0, 0, 0, 12, 0, 0];
        assert_eq!(&raw[..16], &header);
        let body = [
            0x00, 0x10, 0x00, 0x00, 0xf0, 0xff, 0x00, 0x08, 0x00, // 4096, -4096, 2048
            128,  // sigmoid(0) x 255 = 127.5, rounded away from zero
            128, 128, 128, // f_dc 0
            0, 255, 160, // (ln s + 10) x 16
            128, 128, 128, // x, y, z of the identity
        ];
        assert_eq!(&raw[16..], &body);
        // Version 3: w (index 3) is the largest; the three others are zero.
        let mut raw = Vec::new();
        GzDecoder::new(&to_bytes(&g, 3).unwrap()[..]).read_to_end(&mut raw).unwrap();
        assert_eq!(u32::from_le_bytes(raw[raw.len() - 4..].try_into().unwrap()), 3 << 30);
        // A quarter turn about y, negated: the largest components tie, the first (y) is kept.
        let h = SQRT1_2;
        let packed = pack_smallest_three([0.0, -h, 0.0, -h]);
        assert_eq!(packed >> 30, 1);
        assert_eq!(packed & 0x3ff, 511, "w, positive once y is made so");
        let q = unpack_smallest_three(packed);
        assert!((q[1] - h).abs() < 1e-3 && (q[3] - h).abs() < 2e-3, "{q:?}");
    }

    #[test]
    fn bad_files_and_gaussians_are_named() {
        let g = scene(3, 1);
        let e = |b: &[u8]| from_bytes(b).unwrap_err().to_string();
        assert!(e(b"ply\n").contains("not a gzip stream"));
        let mut v4 = MAGIC.to_le_bytes().to_vec();
        v4.extend([4, 0, 0, 0]);
        assert!(e(&v4).contains("version 4"));
        // A stream cut short.
        let mut raw = Vec::new();
        GzDecoder::new(&to_bytes(&g, 3).unwrap()[..]).read_to_end(&mut raw).unwrap();
        let gz = |raw: &[u8]| {
            let mut w = GzEncoder::new(Vec::new(), Compression::fast());
            w.write_all(raw).unwrap();
            w.finish().unwrap()
        };
        assert!(e(&gz(&raw[..raw.len() - 1])).contains("need"), "{}", e(&gz(&raw[..raw.len() - 1])));
        let mut other = raw.clone();
        other[4] = 7;
        assert!(e(&gz(&other)).contains("version 7"));
        let mut far = g.clone();
        far.means[4] = 3000.0;
        assert!(to_bytes(&far, 3).unwrap_err().to_string().contains("Gaussian 1"));
        let mut flat = g.clone();
        flat.quats[8..12].fill(0.0);
        assert!(to_bytes(&flat, 2).unwrap_err().to_string().contains("Gaussian 2: its quaternion is zero"));
        assert!(to_bytes(&g, 4).unwrap_err().to_string().contains("version 4"));
    }
}
