//! Gaussians as binary glTF (GLB) with the `KHR_gaussian_splatting` extension: one mesh of one
//! primitive of mode POINTS, whose attributes are the Gaussians' quantities, all f32:
//! - `POSITION` (VEC3, with its bounds as glTF requires);
//! - `KHR_gaussian_splatting:ROTATION` (VEC4): the unit quaternion in glTF's (x, y, z, w);
//! - `KHR_gaussian_splatting:SCALE` (VEC3): the scales, linear;
//! - `KHR_gaussian_splatting:OPACITY` (SCALAR): sigmoid(logit), in [0, 1];
//! - `KHR_gaussian_splatting:SH_DEGREE_0_COEF_0` (VEC3): f_dc (colour = 0.5 + C0 f_dc);
//! - `COLOR_0` (VEC4): the colour (linear, from the sRGB-coded colour) and opacity, which a
//!   viewer without the extension draws as points.
//!
//! The extension object names the ellipse kernel and the colour space `srgb_rec709_display`
//! (Velox's colours are display values, as its PNGs). glTF's world is y up and right-handed, as
//! Velox's; nothing is converted. The extension is listed in `extensionsUsed` only: a viewer
//! without it still shows the points.
//!
//! The file: a 12-byte header (`glTF`, version 2, length), a JSON chunk padded with spaces and a
//! binary chunk, each attribute one buffer view of it, 4-byte aligned.

use std::path::Path;

use serde_json::{json, Value};
use velox_engine::ops::raster::GaussianData;
use velox_engine::{Error, Result};

use crate::ply::{Sh, SH_C0};
use crate::{read_parsed, write_bytes};

/// `glTF`, read as a little-endian u32.
const MAGIC: u32 = 0x4654_6c67;
const JSON_CHUNK: u32 = 0x4e4f_534a;
const BIN_CHUNK: u32 = 0x004e_4942;
pub(crate) const FLOAT: u64 = 5126;
pub(crate) const UNSIGNED_INT: u64 = 5125;
/// Buffer views of vertex attributes and of vertex indices.
const ARRAY_BUFFER: u64 = 34962;
const ELEMENT_ARRAY_BUFFER: u64 = 34963;
/// The extension's name, and the prefix of its attributes.
pub const EXTENSION: &str = "KHR_gaussian_splatting";

fn bad(why: impl Into<String>) -> Error {
    Error::Invalid(why.into())
}

fn srgb_to_linear(c: f32) -> f32 {
    let c = c.clamp(0.0, 1.0);
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

fn attribute(name: &str) -> String {
    format!("{EXTENSION}:{name}")
}

/// The file's bytes for `g` (at least one Gaussian).
pub fn to_bytes(g: &GaussianData) -> Result<Vec<u8>> {
    to_bytes_sh(g, None)
}

/// The degree and index within it of higher coefficient `k` (0 for degree 1's first).
fn degree_of(k: usize) -> (usize, usize) {
    let degree = ((k + 1) as f64).sqrt().floor() as usize;
    let degree = if (degree + 1) * (degree + 1) - 1 <= k { degree + 1 } else { degree };
    (degree, k + 1 - degree * degree)
}

/// [`to_bytes`] with the Gaussians' higher spherical harmonics: coefficient n of degree l as
/// `KHR_gaussian_splatting:SH_DEGREE_l_COEF_n` (VEC3, red green blue).
pub fn to_bytes_sh(g: &GaussianData, sh: Option<&Sh>) -> Result<Vec<u8>> {
    g.check()?;
    let n = g.len();
    if n == 0 {
        return Err(bad("a glTF accessor holds at least one element: there are no Gaussians"));
    }
    let mut rotation = Vec::with_capacity(4 * n);
    for (i, q) in g.quats.chunks_exact(4).enumerate() {
        let l = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        if l.is_nan() || l <= 0.0 {
            return Err(bad(format!("Gaussian {i}: its quaternion is zero")));
        }
        rotation.extend([q[1] / l, q[2] / l, q[3] / l, q[0] / l]);
    }
    let sigmoid = |x: f32| (1.0 / (1.0 + (-x as f64).exp())) as f32;
    let opacity: Vec<f32> = g.opacities.iter().map(|&o| sigmoid(o)).collect();
    let scale: Vec<f32> = g.log_scales.iter().map(|s| s.exp()).collect();
    let dc: Vec<f32> = g.colours.iter().map(|&c| ((c as f64 - 0.5) / SH_C0) as f32).collect();
    let colour: Vec<f32> = (0..n)
        .flat_map(|i| [0, 1, 2].map(|k| srgb_to_linear(g.colours[3 * i + k])).into_iter().chain([opacity[i]]))
        .collect();
    let columns: [(String, &str, &[f32]); 6] = [
        ("POSITION".into(), "VEC3", &g.means),
        ("COLOR_0".into(), "VEC4", &colour),
        (attribute("ROTATION"), "VEC4", &rotation),
        (attribute("SCALE"), "VEC3", &scale),
        (attribute("OPACITY"), "SCALAR", &opacity),
        (attribute("SH_DEGREE_0_COEF_0"), "VEC3", &dc),
    ];
    let mut buffer = Buffer::default();
    let mut attributes = serde_json::Map::new();
    for (name, kind, values) in &columns {
        attributes.insert(name.clone(), json!(buffer.floats(values, kind, name == "POSITION")));
    }
    if let Some(sh) = sh {
        if sh.coeffs.len() != n * sh.stride() {
            return Err(bad(format!(
                "spherical harmonics: {} coefficients for {n} Gaussians",
                sh.coeffs.len()
            )));
        }
        let k = Sh::per_channel(sh.degree);
        for j in 0..k {
            let values: Vec<f32> = sh
                .coeffs
                .chunks_exact(3 * k)
                .flat_map(|rest| [rest[j], rest[k + j], rest[2 * k + j]])
                .collect();
            let (l, m) = degree_of(j);
            attributes.insert(
                attribute(&format!("SH_DEGREE_{l}_COEF_{m}")),
                json!(buffer.floats(&values, "VEC3", false)),
            );
        }
    }
    let gltf = json!({
        "asset": { "version": "2.0", "generator": "Velox" },
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": [{ "mesh": 0 }],
        "meshes": [{ "primitives": [{
            "attributes": attributes,
            "mode": 0,
            "extensions": { EXTENSION: {
                "kernel": "ellipse",
                "colorSpace": "srgb_rec709_display",
                "projection": "perspective",
                "sortingMethod": "cameraDistance"
            } }
        }] }],
    });
    buffer.pack(gltf)
}

/// A glTF's one buffer in the making: each accessor its own tightly packed buffer view.
#[derive(Default)]
pub(crate) struct Buffer {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Buffer {
    fn add(&mut self, bytes: impl Iterator<Item = [u8; 4]>, target: u64, accessor: Value) -> usize {
        let offset = self.bin.len();
        self.bin.extend(bytes.flatten());
        let length = self.bin.len() - offset;
        self.views.push(json!({ "buffer": 0, "byteOffset": offset, "byteLength": length, "target": target }));
        let mut accessor = accessor;
        accessor["bufferView"] = json!(self.views.len() - 1);
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }

    /// An accessor of f32 `values` of glTF type `kind` (VEC3: with the bounds, which glTF
    /// requires of POSITION, when `bounds`); returns its index.
    pub(crate) fn floats(&mut self, values: &[f32], kind: &str, bounds: bool) -> usize {
        let width = match kind {
            "SCALAR" => 1,
            "VEC3" => 3,
            _ => 4,
        };
        let mut accessor = json!({ "componentType": FLOAT, "count": values.len() / width, "type": kind });
        if bounds {
            let bound = |pick: fn(f32, f32) -> f32| -> Vec<f32> {
                (0..width)
                    .map(|a| values.iter().skip(a).step_by(width).copied().reduce(pick).unwrap_or(0.0))
                    .collect()
            };
            accessor["min"] = json!(bound(f32::min));
            accessor["max"] = json!(bound(f32::max));
        }
        self.add(values.iter().map(|v| v.to_le_bytes()), ARRAY_BUFFER, accessor)
    }

    /// An accessor of u32 vertex indices; returns its index.
    pub(crate) fn indices(&mut self, values: &[u32]) -> usize {
        let accessor = json!({ "componentType": UNSIGNED_INT, "count": values.len(), "type": "SCALAR" });
        self.add(values.iter().map(|v| v.to_le_bytes()), ELEMENT_ARRAY_BUFFER, accessor)
    }

    /// The GLB file of `gltf` (its `buffers`, `bufferViews` and `accessors` set from here).
    pub(crate) fn pack(self, mut gltf: Value) -> Result<Vec<u8>> {
        gltf["buffers"] = json!([{ "byteLength": self.bin.len() }]);
        gltf["bufferViews"] = Value::Array(self.views);
        gltf["accessors"] = Value::Array(self.accessors);
        pack(&gltf, &self.bin)
    }
}

/// A GLB file of the glTF `gltf` and its binary chunk `bin`.
fn pack(gltf: &Value, bin: &[u8]) -> Result<Vec<u8>> {
    let mut text = serde_json::to_vec(gltf).map_err(|e| bad(e.to_string()))?;
    while !text.len().is_multiple_of(4) {
        text.push(b' ');
    }
    let mut bin = bin.to_vec();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + text.len() + 8 + bin.len();
    let total = u32::try_from(total).map_err(|_| bad("the GLB would pass 4 GiB"))?;
    let mut out = Vec::with_capacity(total as usize);
    for w in [MAGIC, 2, total, text.len() as u32, JSON_CHUNK] {
        out.extend_from_slice(&w.to_le_bytes());
    }
    out.extend_from_slice(&text);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(&BIN_CHUNK.to_le_bytes());
    out.extend_from_slice(&bin);
    Ok(out)
}

/// Writes `g` to `path` (atomically).
pub fn write(path: &Path, g: &GaussianData) -> Result<()> {
    write_bytes(path, &to_bytes(g)?)
}

/// Reads Gaussians from a GLB file.
pub fn read(path: &Path) -> Result<GaussianData> {
    read_parsed(path, from_bytes)
}

/// The glTF and the binary chunk of a GLB file.
pub(crate) fn unpack(bytes: &[u8]) -> Result<(Value, &[u8])> {
    let word = |at: usize| bytes.get(at..at + 4).map(|b| u32::from_le_bytes(b.try_into().unwrap()));
    if word(0) != Some(MAGIC) {
        return Err(bad("not a GLB file: it does not start with `glTF`"));
    }
    if word(4) != Some(2) {
        return Err(bad(format!("glTF version {:?} is not read: 2 is", word(4))));
    }
    if word(8) != Some(bytes.len() as u32) {
        return Err(bad(format!("the header says {:?} bytes, the file has {}", word(8), bytes.len())));
    }
    let chunk = |at: usize, kind: u32, name: &str| -> Result<&[u8]> {
        let len = word(at).ok_or_else(|| bad(format!("the file ends before its {name} chunk")))? as usize;
        if word(at + 4) != Some(kind) {
            return Err(bad(format!("the chunk at byte {at} is not the {name} chunk")));
        }
        bytes
            .get(at + 8..at + 8 + len)
            .ok_or_else(|| bad(format!("the {name} chunk runs past the file's end")))
    };
    let text = chunk(12, JSON_CHUNK, "JSON")?;
    let bin = chunk(12 + 8 + text.len(), BIN_CHUNK, "binary")?;
    let gltf: Value = serde_json::from_slice(text).map_err(|e| bad(format!("the JSON chunk: {e}")))?;
    Ok((gltf, bin))
}

/// The bytes of accessor `index` of `gltf` in `bin`: `width` components of 4 bytes of
/// `component` type each, tightly packed (`name` says which in errors).
pub(crate) fn accessor<'a>(
    gltf: &Value,
    bin: &'a [u8],
    index: u64,
    width: usize,
    component: u64,
    name: &str,
) -> Result<&'a [u8]> {
    let a = &gltf["accessors"][index as usize];
    let view = &gltf["bufferViews"][a["bufferView"].as_u64().unwrap_or(u64::MAX) as usize];
    if a["componentType"].as_u64() != Some(component) {
        return Err(bad(format!(
            "{name}: component type {} is not read: {component} is",
            a["componentType"]
        )));
    }
    if view["byteStride"].as_u64().is_some_and(|s| s != 4 * width as u64) {
        return Err(bad(format!("{name}: interleaved buffer views are not read")));
    }
    let count = a["count"].as_u64().unwrap_or(0) as usize;
    let start = (view["byteOffset"].as_u64().unwrap_or(0) + a["byteOffset"].as_u64().unwrap_or(0)) as usize;
    bin.get(start..start.saturating_add(4 * width * count))
        .ok_or_else(|| bad(format!("{name}: {count} values run past the binary chunk")))
}

/// Parses the Gaussians of a GLB's first primitive with `KHR_gaussian_splatting` whose
/// attributes are f32 (as [`to_bytes`] writes them); the colour comes from the degree-0
/// coefficient, higher degrees are skipped.
pub fn from_bytes(bytes: &[u8]) -> Result<GaussianData> {
    Ok(from_bytes_sh(bytes)?.0)
}

/// [`from_bytes`] with the higher spherical harmonics the primitive holds (every degree up to
/// the highest whole one, 3 at most), in the PLY's order.
pub fn from_bytes_sh(bytes: &[u8]) -> Result<(GaussianData, Option<Sh>)> {
    let (gltf, bin) = unpack(bytes)?;
    let primitive = gltf["meshes"]
        .as_array()
        .into_iter()
        .flatten()
        .flat_map(|m| m["primitives"].as_array().into_iter().flatten())
        .find(|p| p["extensions"][EXTENSION].is_object())
        .ok_or_else(|| bad(format!("no primitive has the {EXTENSION} extension")))?;
    let column = |name: &str, width: usize| -> Result<Vec<f32>> {
        let index = primitive["attributes"][name]
            .as_u64()
            .ok_or_else(|| bad(format!("the primitive has no {name} attribute")))?;
        accessor(&gltf, bin, index, width, FLOAT, name)?
            .chunks_exact(4)
            .map(|b| Ok(f32::from_le_bytes(b.try_into().unwrap())))
            .collect()
    };
    let means = column("POSITION", 3)?;
    let rotation = column(&attribute("ROTATION"), 4)?;
    let scale = column(&attribute("SCALE"), 3)?;
    let opacity = column(&attribute("OPACITY"), 1)?;
    let dc = column(&attribute("SH_DEGREE_0_COEF_0"), 3)?;
    let n = opacity.len();
    if [means.len(), rotation.len(), scale.len(), dc.len()] != [3 * n, 4 * n, 3 * n, 3 * n] {
        return Err(bad("the attributes' counts differ"));
    }
    if let Some(s) = scale.iter().find(|s| s.is_nan() || **s <= 0.0) {
        return Err(bad(format!("a scale of {s}: the extension's scales are linear and positive")));
    }
    if let Some(o) = opacity.iter().find(|o| !(0.0..=1.0).contains(*o)) {
        return Err(bad(format!("an opacity of {o}: the extension's opacities lie in [0, 1]")));
    }
    let logit = |o: f32| {
        let o = (o as f64).clamp(1e-7, 1.0 - 1e-7);
        (o / (1.0 - o)).ln() as f32
    };
    let mut higher = Vec::new();
    for j in 0..Sh::per_channel(3) {
        let (l, m) = degree_of(j);
        let name = attribute(&format!("SH_DEGREE_{l}_COEF_{m}"));
        if primitive["attributes"][&name].is_null() {
            break;
        }
        let values = column(&name, 3)?;
        if values.len() != 3 * n {
            return Err(bad(format!("{name}: its count differs from the other attributes'")));
        }
        higher.push(values);
    }
    let sh = match higher.len() {
        0 => None,
        k if [3, 8, 15].contains(&k) => {
            let degree = [3, 8, 15].iter().position(|&c| c == k).unwrap() + 1;
            let mut coeffs = vec![0.0f32; n * 3 * k];
            for (j, values) in higher.iter().enumerate() {
                for i in 0..n {
                    for c in 0..3 {
                        coeffs[i * 3 * k + c * k + j] = values[3 * i + c];
                    }
                }
            }
            Some(Sh { degree, coeffs })
        }
        k => return Err(bad(format!("{k} higher SH coefficients: a degree must be whole (3, 8 or 15)"))),
    };
    let g = GaussianData {
        means,
        log_scales: scale.iter().map(|s| s.ln()).collect(),
        quats: rotation.chunks_exact(4).flat_map(|q| [q[3], q[0], q[1], q[2]]).collect(),
        opacities: opacity.into_iter().map(logit).collect(),
        colours: dc.iter().map(|&d| (0.5 + SH_C0 * d as f64) as f32).collect(),
    };
    Ok((g, sh))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(n: usize, seed: u64) -> GaussianData {
        crate::test_gaussians(n, seed, 2.0, (-6.0, 0.0))
    }

    #[test]
    fn gaussians_round_trip() {
        let g = scene(301, 4);
        let bytes = to_bytes(&g).unwrap();
        assert_eq!(bytes.len() % 4, 0);
        let r = from_bytes(&bytes).unwrap();
        assert_eq!(r.means, g.means);
        let close = |a: &[f32], b: &[f32], tol: f32, what: &str| {
            for (x, y) in a.iter().zip(b) {
                assert!((x - y).abs() <= tol * x.abs().max(1.0), "{what}: {x} -> {y}");
            }
        };
        close(&g.log_scales, &r.log_scales, 1e-6, "log scale");
        close(&g.opacities, &r.opacities, 1e-4, "opacity logit");
        close(&g.colours, &r.colours, 1e-6, "colour");
        let unit: Vec<f32> = g
            .quats
            .chunks(4)
            .flat_map(|q| {
                let l = q.iter().map(|v| v * v).sum::<f32>().sqrt();
                q.iter().map(move |v| v / l).collect::<Vec<_>>()
            })
            .collect();
        close(&unit, &r.quats, 1e-6, "quaternion");
        // The JSON says what a viewer needs: the extension, POINTS, the position bounds.
        let len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
        let gltf: Value = serde_json::from_slice(&bytes[20..20 + len]).unwrap();
        assert_eq!(gltf["extensionsUsed"], json!([EXTENSION]));
        let p = &gltf["meshes"][0]["primitives"][0];
        assert_eq!(p["mode"], 0);
        assert_eq!(p["extensions"][EXTENSION]["kernel"], "ellipse");
        let position = &gltf["accessors"][p["attributes"]["POSITION"].as_u64().unwrap() as usize];
        let xs = g.means.iter().step_by(3).copied();
        assert_eq!(position["min"][0].as_f64().unwrap() as f32, xs.clone().reduce(f32::min).unwrap());
        assert_eq!(position["max"][0].as_f64().unwrap() as f32, xs.reduce(f32::max).unwrap());
    }

    #[test]
    fn spherical_harmonics_round_trip_by_degree_and_coefficient() {
        assert_eq!((0..15).map(degree_of).collect::<Vec<_>>()[..4], [(1, 0), (1, 1), (1, 2), (2, 0)]);
        assert_eq!(degree_of(7), (2, 4));
        assert_eq!(degree_of(8), (3, 0));
        assert_eq!(degree_of(14), (3, 6));
        let g = scene(20, 6);
        for degree in 1..=3 {
            let k = Sh::per_channel(degree);
            let sh = Sh { degree, coeffs: (0..20 * 3 * k).map(|i| i as f32 * 0.01 - 0.3).collect() };
            let bytes = to_bytes_sh(&g, Some(&sh)).unwrap();
            assert_eq!(from_bytes_sh(&bytes).unwrap().1, Some(sh.clone()));
            let len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
            let gltf: Value = serde_json::from_slice(&bytes[20..20 + len]).unwrap();
            let attributes = &gltf["meshes"][0]["primitives"][0]["attributes"];
            let last = format!("{EXTENSION}:SH_DEGREE_{degree}_COEF_{}", 2 * degree);
            assert!(attributes[&last].is_u64(), "{last}");
        }
    }

    #[test]
    fn bad_files_are_named() {
        let e = |b: &[u8]| from_bytes(b).unwrap_err().to_string();
        assert!(e(b"ply\n").contains("not a GLB"));
        let bytes = to_bytes(&scene(5, 1)).unwrap();
        assert!(e(&bytes[..bytes.len() - 4]).contains("the header says"));
        assert!(to_bytes(&GaussianData::default()).unwrap_err().to_string().contains("no Gaussians"));
    }
}
