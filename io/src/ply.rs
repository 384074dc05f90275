//! Gaussians as binary little-endian PLY in the layout of 3D Gaussian splatting, which common
//! splat viewers open: one `vertex` element with float properties x, y, z, nx, ny, nz (zeros),
//! f_dc_0..2 (degree-0 spherical harmonics: colour = 0.5 + C0 f_dc), opacity (logit),
//! scale_0..2 (log), rot_0..3 (w, x, y, z).
//!
//! The reader takes any property order, float or double (and integer) properties, and ignores
//! properties it does not use and elements after the vertices. The body must hold exactly the
//! items the header declares, and every value read must be finite. [`Header`] is the one PLY
//! header parser of the project (the data crate's point clouds use it too).
//!
//! Higher spherical harmonics (`f_rest_0..`, degree 1 to 3: 9, 24 or 45 of them, after
//! f_dc_2 as 3D Gaussian splatting writes them) are read and written by [`read_sh`] and
//! [`to_bytes_sh`] as an [`Sh`] beside the Gaussians (the renderer colours each Gaussian along
//! the view from them, `raster::sh_colours`, and so does the viewer); [`read`] keeps the
//! degree-0 colour alone.

use std::path::Path;

use velox_engine::ops::raster::GaussianData;
use velox_engine::{Error, Result};

use crate::{read_parsed, write_bytes};

/// The degree-0 spherical harmonic, 1 / (2 sqrt(pi)).
pub const SH_C0: f64 = 0.28209479177387814;

const PROPERTIES: [&str; 17] = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
    "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
];

/// The file's bytes for `g`.
pub fn to_bytes(g: &GaussianData) -> Result<Vec<u8>> {
    to_bytes_sh(g, None)
}

/// The file's bytes for `g` with its higher spherical harmonics `sh` (`f_rest_*` after
/// f_dc_2, as 3D Gaussian splatting writes them).
pub fn to_bytes_sh(g: &GaussianData, sh: Option<&Sh>) -> Result<Vec<u8>> {
    g.check()?;
    let n = g.len();
    let rest = match sh {
        Some(sh) => {
            if !(1..=3).contains(&sh.degree) || sh.coeffs.len() != n * sh.stride() {
                return Err(Error::Shape(format!(
                    "spherical harmonics of degree {} for {n} Gaussians need {} coefficients, got {}",
                    sh.degree,
                    n * sh.stride(),
                    sh.coeffs.len()
                )));
            }
            sh.stride()
        }
        None => 0,
    };
    let mut out = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n").into_bytes();
    for p in &PROPERTIES[..9] {
        out.extend_from_slice(format!("property float {p}\n").as_bytes());
    }
    for k in 0..rest {
        out.extend_from_slice(format!("property float f_rest_{k}\n").as_bytes());
    }
    for p in &PROPERTIES[9..] {
        out.extend_from_slice(format!("property float {p}\n").as_bytes());
    }
    out.extend_from_slice(b"end_header\n");
    out.reserve(n * (PROPERTIES.len() + rest) * 4);
    for i in 0..n {
        let dc = |k: usize| ((g.colours[3 * i + k] as f64 - 0.5) / SH_C0) as f32;
        let head =
            [g.means[3 * i], g.means[3 * i + 1], g.means[3 * i + 2], 0.0, 0.0, 0.0, dc(0), dc(1), dc(2)];
        let coeffs = sh.map(|sh| &sh.coeffs[i * rest..(i + 1) * rest]).unwrap_or(&[]);
        let tail = [
            g.opacities[i],
            g.log_scales[3 * i],
            g.log_scales[3 * i + 1],
            g.log_scales[3 * i + 2],
            g.quats[4 * i],
            g.quats[4 * i + 1],
            g.quats[4 * i + 2],
            g.quats[4 * i + 3],
        ];
        for v in head.iter().chain(coeffs).chain(&tail) {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    Ok(out)
}

/// Writes `g` to `path` (atomically).
pub fn write(path: &Path, g: &GaussianData) -> Result<()> {
    write_bytes(path, &to_bytes(g)?)
}

/// Spherical-harmonic coefficients of degrees 1 to `degree` of N Gaussians, in the PLY's
/// order: per Gaussian, `3 K` values (K = (degree + 1)^2 - 1), all K of red, then green, then
/// blue; coefficient k of a channel is the (k + 1)-th basis function, m = -l..l by degree.
#[derive(Clone, Debug, PartialEq)]
pub struct Sh {
    pub degree: usize,
    pub coeffs: Vec<f32>,
}

impl Sh {
    /// Coefficients per channel of a Gaussian (degree 0 excluded).
    pub fn per_channel(degree: usize) -> usize {
        velox_engine::ops::raster::sh::per_channel(degree)
    }
    /// Values per Gaussian.
    pub fn stride(&self) -> usize {
        3 * Sh::per_channel(self.degree)
    }
}

/// The colour a Gaussian shows along a unit direction, its higher harmonics in this order:
/// the engine's f64 reference, which its kernel and `velox view`'s shader are tested against.
pub use velox_engine::ops::raster::reference::sh_colour;

/// Reads Gaussians from `path`.
pub fn read(path: &Path) -> Result<GaussianData> {
    read_parsed(path, from_bytes)
}

/// The scalar types of PLY properties.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    pub(crate) fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    /// Bytes of one value.
    pub fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
    /// The value at the start of `b` (little-endian), which holds at least [`Scalar::size`] bytes.
    pub fn read(self, b: &[u8]) -> f64 {
        match self {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::I32 => i32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
            Scalar::U32 => u32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
            Scalar::F32 => f32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
            Scalar::F64 => f64::from_le_bytes(b[..8].try_into().unwrap()),
        }
    }
}

/// One element of a PLY header: its name, how many items it declares, and the properties of
/// an item in file order.
#[derive(Clone, Debug, PartialEq)]
pub struct Element {
    pub name: String,
    pub count: usize,
    pub properties: Vec<(String, Scalar)>,
    /// List properties (a mesh's `face` element): name, count type, item type. An element
    /// with one has no fixed size: nothing after it can be found, and the file's length is
    /// checked by its reader ([`crate::mesh`]).
    pub lists: Vec<(String, Scalar, Scalar)>,
}

impl Element {
    /// Bytes of one item.
    pub fn stride(&self) -> usize {
        self.properties.iter().map(|p| p.1.size()).sum()
    }
}

/// The header of a binary little-endian PLY file with scalar properties (every reader of the
/// project parses its PLY files with it).
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    pub elements: Vec<Element>,
    /// Offset of the first byte after the `end_header` line.
    pub body_start: usize,
}

fn bad(why: impl Into<String>) -> Error {
    Error::Invalid(why.into())
}

impl Header {
    /// Parses the header at the start of `bytes`. Check the body with [`Header::check_length`]
    /// before reading items.
    pub fn parse(bytes: &[u8]) -> Result<Header> {
        const END: &[u8] = b"end_header";
        let end = bytes
            .windows(END.len())
            .position(|w| w == END)
            .ok_or_else(|| bad("not a PLY file: no `end_header` line"))?;
        let body_start = bytes[end..]
            .iter()
            .position(|&b| b == b'\n')
            .map(|p| end + p + 1)
            .ok_or_else(|| bad("the header's `end_header` line has no line end"))?;
        let header = std::str::from_utf8(&bytes[..end]).map_err(|_| bad("the PLY header is not text"))?;
        let mut lines = header.lines().map(str::trim);
        if lines.next() != Some("ply") {
            return Err(bad("not a PLY file: it does not start with `ply`"));
        }
        let mut elements: Vec<Element> = Vec::new();
        let mut format_seen = false;
        for line in lines {
            let words: Vec<&str> = line.split_whitespace().collect();
            match words.as_slice() {
                [] | ["comment", ..] | ["obj_info", ..] => {}
                ["format", "binary_little_endian", _] => format_seen = true,
                ["format", other, _] => {
                    return Err(bad(format!(
                        "PLY format `{other}` is not supported: only binary_little_endian files are read"
                    )))
                }
                ["element", name, count] => elements.push(Element {
                    name: name.to_string(),
                    count: count
                        .parse()
                        .map_err(|_| bad(format!("element {name}: count `{count}` is not a number")))?,
                    properties: Vec::new(),
                    lists: Vec::new(),
                }),
                ["property", "list", count, item, name] => {
                    let e = elements
                        .last_mut()
                        .ok_or_else(|| bad(format!("property `{name}` before any element")))?;
                    let scalar = |t: &str| {
                        Scalar::parse(t)
                            .ok_or_else(|| bad(format!("list property {name}: unknown type `{t}`")))
                    };
                    e.lists.push((name.to_string(), scalar(count)?, scalar(item)?));
                }
                ["property", ty, name] => {
                    let e = elements
                        .last_mut()
                        .ok_or_else(|| bad(format!("property `{name}` before any element")))?;
                    let s = Scalar::parse(ty)
                        .ok_or_else(|| bad(format!("property {name}: unknown type `{ty}`")))?;
                    e.properties.push((name.to_string(), s));
                }
                _ => return Err(bad(format!("unreadable PLY header line `{line}`"))),
            }
        }
        if !format_seen {
            return Err(bad("the PLY header has no `format binary_little_endian 1.0` line"));
        }
        Ok(Header { elements, body_start })
    }

    /// Offset of the first item of element `name` from the file's start, and the element.
    /// Valid once [`Header::check_length`] has passed.
    pub fn find(&self, name: &str) -> Option<(usize, &Element)> {
        let mut at = self.body_start;
        for e in &self.elements {
            if e.name == name {
                return Some((at, e));
            }
            if !e.lists.is_empty() {
                return None;
            }
            at = at.saturating_add(e.count.saturating_mul(e.stride()));
        }
        None
    }

    /// Checks that the body after the header holds exactly the items the header declares: a
    /// file with fewer bytes is truncated, one with more does not match its header (a property
    /// declared `uchar` whose data is `float`, say). `bytes` is the whole file.
    pub fn check_length(&self, bytes: &[u8]) -> Result<()> {
        if let Some(e) = self.elements.iter().find(|e| !e.lists.is_empty()) {
            return Err(bad(format!(
                "element {} has list properties (a mesh's faces): this file is a mesh, read as one",
                e.name
            )));
        }
        let have = bytes.len().saturating_sub(self.body_start);
        // In u128, where no count of a header can overflow.
        let need: u128 = self.elements.iter().map(|e| e.count as u128 * e.stride() as u128).sum();
        let declared = || {
            self.elements
                .iter()
                .map(|e| format!("{} {} of {} bytes", e.count, e.name, e.stride()))
                .collect::<Vec<_>>()
                .join(", ")
        };
        if need > have as u128 {
            return Err(bad(format!(
                "the file is truncated: the header declares {} ({need} bytes after the header), the file has {have}",
                declared()
            )));
        }
        if need < have as u128 {
            return Err(bad(format!(
                "the body does not match the header: the header declares {} ({need} bytes after the header), the file has {have} (a property of the wrong type?)",
                declared()
            )));
        }
        Ok(())
    }
}

/// Reads Gaussians and their higher spherical harmonics (when the file has any) from `path`.
pub fn read_sh(path: &Path) -> Result<(GaussianData, Option<Sh>)> {
    read_parsed(path, from_bytes_sh)
}

/// Parses a PLY file's bytes with their higher spherical harmonics: `f_rest_0..` as 9, 24 or
/// 45 properties (degree 1, 2 or 3), or none.
pub fn from_bytes_sh(bytes: &[u8]) -> Result<(GaussianData, Option<Sh>)> {
    let g = from_bytes(bytes)?;
    let header = Header::parse(bytes)?;
    let (at, e) = header.find("vertex").expect("from_bytes found it");
    let mut rest = Vec::new();
    let mut offset = 0;
    for (name, scalar) in &e.properties {
        if let Some(k) = name.strip_prefix("f_rest_").and_then(|k| k.parse::<usize>().ok()) {
            rest.push((k, offset, *scalar));
        }
        offset += scalar.size();
    }
    if rest.is_empty() {
        return Ok((g, None));
    }
    rest.sort_by_key(|r| r.0);
    let degree = match rest.len() {
        9 => 1,
        24 => 2,
        45 => 3,
        n => return Err(bad(format!("{n} f_rest properties: degrees 1, 2 and 3 have 9, 24 and 45"))),
    };
    if let Some(k) = rest.iter().enumerate().find(|(i, r)| r.0 != *i) {
        return Err(bad(format!("f_rest_{} is missing: the f_rest properties must be numbered from 0", k.0)));
    }
    let stride = e.stride();
    let mut coeffs = Vec::with_capacity(e.count * rest.len());
    for i in 0..e.count {
        let row = &bytes[at + i * stride..at + (i + 1) * stride];
        for (k, o, s) in &rest {
            let v = s.read(&row[*o..]) as f32;
            if !v.is_finite() {
                return Err(bad(format!("vertex {i}: f_rest_{k} is not a finite f32")));
            }
            coeffs.push(v);
        }
    }
    Ok((g, Some(Sh { degree, coeffs })))
}

/// Parses a PLY file's bytes. Every value must be finite.
pub fn from_bytes(bytes: &[u8]) -> Result<GaussianData> {
    let header = Header::parse(bytes)?;
    let (at, e) = header.find("vertex").ok_or_else(|| bad("the PLY file has no `vertex` element"))?;
    let column = |name: &str| -> Result<(usize, Scalar)> {
        let mut offset = 0;
        for (p, s) in &e.properties {
            if p == name {
                return Ok((offset, *s));
            }
            offset += s.size();
        }
        Err(bad(format!(
            "the vertex element has no `{name}` property: a 3D Gaussian splatting file needs x, y, z, f_dc_0..2, opacity, scale_0..2 and rot_0..3"
        )))
    };
    let names: Vec<&str> = PROPERTIES.iter().copied().filter(|p| !p.starts_with('n')).collect();
    let used: Vec<(usize, Scalar)> = names.iter().map(|p| column(p)).collect::<Result<_>>()?;
    header.check_length(bytes)?;
    let stride = e.stride();
    let mut g = GaussianData::default();
    for i in 0..e.count {
        let row = &bytes[at + i * stride..at + (i + 1) * stride];
        let v: Vec<f64> = used.iter().map(|&(o, s)| s.read(&row[o..])).collect();
        if let Some(k) = v.iter().position(|x| !(*x as f32).is_finite()) {
            return Err(bad(format!("vertex {i}: {} is {:e}, not a finite f32", names[k], v[k])));
        }
        // v: x y z, f_dc 0..2, opacity, scale 0..2, rot 0..3
        let colour = [v[3], v[4], v[5]].map(|dc| (0.5 + SH_C0 * dc) as f32);
        g.push(
            [v[0] as f32, v[1] as f32, v[2] as f32],
            [v[7] as f32, v[8] as f32, v[9] as f32],
            [v[10] as f32, v[11] as f32, v[12] as f32, v[13] as f32],
            v[6] as f32,
            colour,
        );
    }
    Ok(g)
}
