//! Triangle meshes (the surfaces `velox decode mesh` extracts) as PLY, OBJ and glTF binary,
//! each with its reader:
//! - PLY, binary little-endian: a `vertex` element of float x, y, z, nx, ny, nz and a `face`
//!   element with one list, `vertex_indices` (uchar count, uint indices). The reader takes any
//!   scalar types, other vertex properties, and polygons (fanned into triangles);
//! - OBJ: `v x y z`, `vn x y z` and `f a//a b//b c//c` lines (1-based); the reader takes
//!   `f a`, `a/t`, `a/t/n` and `a//n` corners and negative (relative) indices;
//! - GLB: one primitive of mode TRIANGLES with POSITION (with its bounds), NORMAL and u32
//!   indices.
//!
//! Triangles run counter-clockwise seen from outside, as glTF and OBJ expect.

use std::fmt::Write as _;
use std::path::Path;

use serde_json::json;
use velox_engine::{Error, Result};

use crate::glb::{self, Buffer, FLOAT, UNSIGNED_INT};
use crate::ply::{Header, Scalar};
use crate::{read_parsed, write_bytes};

/// A triangle mesh: vertex positions and triangles (counter-clockwise seen from outside).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

fn bad(why: impl Into<String>) -> Error {
    Error::Invalid(why.into())
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

impl Mesh {
    /// Fails unless every triangle names vertices the mesh has and every position is finite.
    pub fn check(&self) -> Result<()> {
        let n = self.positions.len();
        if let Some((i, t)) =
            self.triangles.iter().enumerate().find(|(_, t)| t.iter().any(|&v| v as usize >= n))
        {
            return Err(bad(format!("triangle {i} names vertex {} of {n}", t.iter().max().unwrap())));
        }
        if let Some(i) = self.positions.iter().position(|p| p.iter().any(|v| !v.is_finite())) {
            return Err(bad(format!("vertex {i} is not finite")));
        }
        Ok(())
    }

    /// Triangle `t`'s corners (f64) and its edges' cross product (its normal times twice its
    /// area: counter-clockwise seen from where it points).
    pub fn face(&self, t: [u32; 3]) -> ([[f64; 3]; 3], [f64; 3]) {
        let p = t.map(|i| self.positions[i as usize].map(f64::from));
        (p, cross(sub(p[1], p[0]), sub(p[2], p[0])))
    }

    /// Per-vertex normals: the area-weighted sum of the triangles' normals around each vertex,
    /// normalised (zero where no triangle has an area).
    pub fn normals(&self) -> Vec<[f32; 3]> {
        let mut n = vec![[0.0f64; 3]; self.positions.len()];
        for &t in &self.triangles {
            let (_, c) = self.face(t);
            for i in t {
                for k in 0..3 {
                    n[i as usize][k] += c[k];
                }
            }
        }
        n.iter()
            .map(|v| {
                let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                if l > 0.0 {
                    v.map(|x| (x / l) as f32)
                } else {
                    [0.0; 3]
                }
            })
            .collect()
    }

    /// The surface's area and the volume it encloses (the divergence theorem: positive when the
    /// triangles face out).
    pub fn area_and_volume(&self) -> (f64, f64) {
        let (mut area, mut volume) = (0.0, 0.0);
        for &t in &self.triangles {
            let (p, c) = self.face(t);
            area += 0.5 * (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
            let d = cross(p[1], p[2]);
            volume += (p[0][0] * d[0] + p[0][1] * d[1] + p[0][2] * d[2]) / 6.0;
        }
        (area, volume)
    }
}

/// The mesh's file formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Ply,
    Obj,
    Glb,
}

impl Format {
    pub const ALL: [Format; 3] = [Format::Ply, Format::Obj, Format::Glb];

    /// The format a path's extension names (.ply, .obj, .glb, any case).
    pub fn of_path(path: &Path) -> Result<Format> {
        let ext = path.extension().map(|e| e.to_string_lossy().to_lowercase()).unwrap_or_default();
        Format::ALL
            .into_iter()
            .find(|f| f.extension() == ext)
            .ok_or_else(|| bad(format!("{}: a mesh is a .ply, .obj or .glb file", path.display())))
    }

    /// The file extension.
    pub fn extension(self) -> &'static str {
        match self {
            Format::Ply => "ply",
            Format::Obj => "obj",
            Format::Glb => "glb",
        }
    }
}

/// The file's bytes for `m` in `format`.
pub fn to_bytes(m: &Mesh, format: Format) -> Result<Vec<u8>> {
    m.check()?;
    let normals = m.normals();
    Ok(match format {
        Format::Ply => {
            let (v, f) = (m.positions.len(), m.triangles.len());
            let mut out = format!(
                "ply\nformat binary_little_endian 1.0\ncomment Velox surface mesh\nelement vertex {v}\n"
            )
            .into_bytes();
            for p in ["x", "y", "z", "nx", "ny", "nz"] {
                out.extend_from_slice(format!("property float {p}\n").as_bytes());
            }
            out.extend_from_slice(
                format!("element face {f}\nproperty list uchar uint vertex_indices\nend_header\n").as_bytes(),
            );
            for (p, n) in m.positions.iter().zip(&normals) {
                for x in p.iter().chain(n) {
                    out.extend_from_slice(&x.to_le_bytes());
                }
            }
            for t in &m.triangles {
                out.push(3);
                for i in t {
                    out.extend_from_slice(&i.to_le_bytes());
                }
            }
            out
        }
        Format::Obj => {
            let mut text = String::from("# Velox surface mesh\n");
            for p in &m.positions {
                let _ = writeln!(text, "v {} {} {}", p[0], p[1], p[2]);
            }
            for n in &normals {
                let _ = writeln!(text, "vn {} {} {}", n[0], n[1], n[2]);
            }
            for t in &m.triangles {
                let [a, b, c] = t.map(|i| i + 1);
                let _ = writeln!(text, "f {a}//{a} {b}//{b} {c}//{c}");
            }
            text.into_bytes()
        }
        Format::Glb => {
            if m.triangles.is_empty() {
                return Err(bad("a glTF accessor holds at least one element: the mesh has no triangles"));
            }
            let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
            let mut buffer = Buffer::default();
            let position = buffer.floats(&flat(&m.positions), "VEC3", true);
            let normal = buffer.floats(&flat(&normals), "VEC3", false);
            let indices = buffer.indices(&m.triangles.iter().flatten().copied().collect::<Vec<u32>>());
            let gltf = json!({
                "asset": { "version": "2.0", "generator": "Velox" },
                "scene": 0,
                "scenes": [{ "nodes": [0] }],
                "nodes": [{ "mesh": 0 }],
                "meshes": [{ "primitives": [{
                    "attributes": { "POSITION": position, "NORMAL": normal },
                    "indices": indices,
                    "mode": 4
                }] }],
            });
            buffer.pack(gltf)?
        }
    })
}

/// Writes `m` to `path` (atomically) in `format`.
pub fn write(path: &Path, m: &Mesh, format: Format) -> Result<()> {
    write_bytes(path, &to_bytes(m, format)?)
}

/// Reads a mesh from `path`, in the format its extension names.
pub fn read(path: &Path) -> Result<Mesh> {
    let format = Format::of_path(path)?;
    read_parsed(path, |bytes| from_bytes(bytes, format))
}

/// Parses a mesh file's bytes.
pub fn from_bytes(bytes: &[u8], format: Format) -> Result<Mesh> {
    let m = match format {
        Format::Ply => from_ply(bytes)?,
        Format::Obj => from_obj(bytes)?,
        Format::Glb => from_glb(bytes)?,
    };
    m.check()?;
    Ok(m)
}

/// Polygon `corners` as a fan of triangles.
fn fan(corners: &[u32], out: &mut Vec<[u32; 3]>) {
    for k in 1..corners.len().saturating_sub(1) {
        out.push([corners[0], corners[k], corners[k + 1]]);
    }
}

fn from_ply(bytes: &[u8]) -> Result<Mesh> {
    let header = Header::parse(bytes)?;
    let (at, vertex) = header.find("vertex").ok_or_else(|| bad("the PLY file has no `vertex` element"))?;
    if !vertex.lists.is_empty() {
        return Err(bad("the vertex element has list properties"));
    }
    let column = |name: &str| -> Result<(usize, Scalar)> {
        let mut offset = 0;
        for (p, s) in &vertex.properties {
            if p == name {
                return Ok((offset, *s));
            }
            offset += s.size();
        }
        Err(bad(format!("the vertex element has no `{name}` property")))
    };
    let xyz = [column("x")?, column("y")?, column("z")?];
    let stride = vertex.stride();
    let faces_at = at.saturating_add(vertex.count.saturating_mul(stride));
    if faces_at > bytes.len() {
        return Err(bad(format!("the file is truncated: {} vertices of {stride} bytes", vertex.count)));
    }
    let positions =
        (0..vertex.count).map(|i| xyz.map(|(o, s)| s.read(&bytes[at + i * stride + o..]) as f32)).collect();
    let face = header.elements.iter().position(|e| e.name == "face");
    let Some(face) = face.map(|k| &header.elements[k]) else {
        return Err(bad("the PLY file has no `face` element: it is points, not a mesh"));
    };
    if header.elements.iter().position(|e| e.name == "vertex")
        > header.elements.iter().position(|e| e.name == "face")
        || header.elements.last().map(|e| &e.name) != Some(&face.name)
        || header.elements.len() != 2
    {
        return Err(bad("a mesh PLY holds a vertex element, then a face element"));
    }
    let [(name, count_type, index_type)] = face.lists.as_slice() else {
        return Err(bad("the face element must hold one list property, its vertex indices"));
    };
    if !face.properties.is_empty() || !matches!(name.as_str(), "vertex_indices" | "vertex_index") {
        return Err(bad("the face element must hold only its vertex indices"));
    }
    let mut triangles = Vec::with_capacity(face.count);
    let mut at = faces_at;
    let mut corners = Vec::new();
    for f in 0..face.count {
        let truncated = || bad(format!("the file is truncated in face {f}"));
        let n = bytes.get(at..at + count_type.size()).map(|b| count_type.read(b)).ok_or_else(truncated)?;
        at += count_type.size();
        if !(3.0..=255.0).contains(&n) {
            return Err(bad(format!("face {f} has {n} corners")));
        }
        corners.clear();
        for _ in 0..n as usize {
            let i =
                bytes.get(at..at + index_type.size()).map(|b| index_type.read(b)).ok_or_else(truncated)?;
            at += index_type.size();
            if !(i >= 0.0 && i <= u32::MAX as f64) {
                return Err(bad(format!("face {f} names vertex {i}")));
            }
            corners.push(i as u32);
        }
        fan(&corners, &mut triangles);
    }
    if at != bytes.len() {
        return Err(bad(format!(
            "{} bytes follow the last face: the body does not match the header",
            bytes.len() - at
        )));
    }
    Ok(Mesh { positions, triangles })
}

fn from_obj(bytes: &[u8]) -> Result<Mesh> {
    let text = std::str::from_utf8(bytes).map_err(|_| bad("an OBJ file is text; this is not"))?;
    let mut m = Mesh::default();
    let mut corners = Vec::new();
    for (k, line) in text.lines().enumerate() {
        let words: Vec<&str> = line.split_whitespace().collect();
        let at = || format!("line {}", k + 1);
        match words.as_slice() {
            ["v", x, y, z, ..] => {
                let p = [x, y, z].map(|v| v.parse::<f32>());
                match p {
                    [Ok(x), Ok(y), Ok(z)] => m.positions.push([x, y, z]),
                    _ => return Err(bad(format!("{}: `{line}` is not a vertex", at()))),
                }
            }
            ["f", rest @ ..] => {
                corners.clear();
                for c in rest {
                    let first = c.split('/').next().unwrap_or("");
                    let i: i64 =
                        first.parse().map_err(|_| bad(format!("{}: corner `{c}` is not an index", at())))?;
                    let n = m.positions.len() as i64;
                    let index = if i < 0 { n + i } else { i - 1 };
                    if index < 0 || index >= n {
                        return Err(bad(format!("{}: corner {i} names no vertex read so far ({n})", at())));
                    }
                    corners.push(index as u32);
                }
                if corners.len() < 3 {
                    return Err(bad(format!("{}: a face of {} corners", at(), corners.len())));
                }
                fan(&corners, &mut m.triangles);
            }
            _ => {}
        }
    }
    Ok(m)
}

fn from_glb(bytes: &[u8]) -> Result<Mesh> {
    let (gltf, bin) = glb::unpack(bytes)?;
    let primitive = &gltf["meshes"][0]["primitives"][0];
    if primitive["mode"].as_u64().unwrap_or(4) != 4 {
        return Err(bad("the first primitive is not of triangles (mode 4)"));
    }
    let position = primitive["attributes"]["POSITION"]
        .as_u64()
        .ok_or_else(|| bad("the first primitive has no POSITION"))?;
    let values = glb::accessor(&gltf, bin, position, 3, FLOAT, "POSITION")?;
    let positions: Vec<[f32; 3]> = values
        .chunks_exact(12)
        .map(|b| std::array::from_fn(|k| f32::from_le_bytes(b[4 * k..4 * k + 4].try_into().unwrap())))
        .collect();
    let triangles = match primitive["indices"].as_u64() {
        Some(index) => glb::accessor(&gltf, bin, index, 1, UNSIGNED_INT, "indices")?
            .chunks_exact(12)
            .map(|b| std::array::from_fn(|k| u32::from_le_bytes(b[4 * k..4 * k + 4].try_into().unwrap())))
            .collect(),
        None => (0..positions.len() as u32 / 3).map(|t| [3 * t, 3 * t + 1, 3 * t + 2]).collect(),
    };
    Ok(Mesh { positions, triangles })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit cube's 8 corners and 12 triangles, facing out.
    fn cube() -> Mesh {
        let positions =
            (0..8).map(|i| [(i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32]).collect();
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        let mut triangles = Vec::new();
        for q in quads {
            fan(&q, &mut triangles);
        }
        Mesh { positions, triangles }
    }

    #[test]
    fn a_cube_round_trips_through_every_format() {
        let m = cube();
        let (area, volume) = m.area_and_volume();
        assert!((area - 6.0).abs() < 1e-9 && (volume - 1.0).abs() < 1e-9, "{area} {volume}: facing out");
        for format in Format::ALL {
            let back = from_bytes(&to_bytes(&m, format).unwrap(), format).unwrap();
            assert_eq!(back, m, "{format:?}");
        }
        // The corner's normal points out along the diagonal.
        let n = m.normals()[7];
        assert!(n.iter().all(|&v| (v - 1.0 / 3f32.sqrt()).abs() < 1e-6), "{n:?}");
    }

    #[test]
    fn other_tools_files_read_and_bad_ones_are_named() {
        // An OBJ with a quad, texture corners and a relative index.
        let obj = b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1 -1/1\n";
        let m = from_bytes(obj, Format::Obj).unwrap();
        assert_eq!(m.triangles, [[0, 1, 2], [0, 2, 3]]);
        let e = |b: &[u8], f| from_bytes(b, f).unwrap_err().to_string();
        assert!(e(b"v 0 0 0\nf 1 2 3\n", Format::Obj).contains("line 2"));
        // A PLY of int indices with a quad; one cut short; one of points.
        let mut ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty double x\nproperty double y\nproperty double z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
        for p in [[0.0f64, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]] {
            for v in p {
                ply.extend_from_slice(&v.to_le_bytes());
            }
        }
        ply.push(4);
        for i in [0i32, 1, 2, 3] {
            ply.extend_from_slice(&i.to_le_bytes());
        }
        assert_eq!(from_bytes(&ply, Format::Ply).unwrap().triangles, [[0, 1, 2], [0, 2, 3]]);
        assert!(e(&ply[..ply.len() - 1], Format::Ply).contains("truncated in face 0"));
        let points = crate::ply::to_bytes(&Default::default()).unwrap();
        assert!(e(&points, Format::Ply).contains("no `face` element"));
        let mut bad_index = cube();
        bad_index.triangles[3][1] = 8;
        assert!(to_bytes(&bad_index, Format::Obj)
            .unwrap_err()
            .to_string()
            .contains("triangle 3 names vertex 8"));
        // The points reader refuses a mesh by name.
        let header = Header::parse(&to_bytes(&cube(), Format::Ply).unwrap()).unwrap();
        assert!(header.check_length(&[]).unwrap_err().to_string().contains("this file is a mesh"));
    }
}
