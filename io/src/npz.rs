//! numpy's `.npz` archives (what `np.savez` and `np.savez_compressed` write: a zip of `.npy`
//! files, stored or deflated, with zip64 sizes), read into arrays of numbers: the layout of
//! TAPVid-3D's files and of the predictions its evaluation scores.
//!
//! An `.npy` member holds a little-endian array of bools, integers or floats in C order
//! (`fortran_order` is refused, as is a big-endian type). An array of Python objects (`|O`,
//! pickled: TAPVid-3D's `images_jpeg_bytes`) is kept as its raw bytes, from which
//! [`first_jpeg_size`] reads the size of the first JPEG it holds. Every error names the file
//! and the member.
//!
//! Tests: below (arrays written by hand), and `python/tests` (archives numpy writes, stored
//! and deflated, with its zip64 fields).

use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;

use velox_engine::Result;

use crate::{content_error, read_error};

/// The values of an array.
#[derive(Clone, Debug, PartialEq)]
pub enum Values {
    Bool(Vec<bool>),
    Int(Vec<i64>),
    Float(Vec<f64>),
    /// A pickled array of Python objects, as its bytes.
    Object(Vec<u8>),
}

/// One array of an archive.
#[derive(Clone, Debug, PartialEq)]
pub struct Array {
    pub shape: Vec<usize>,
    /// The numpy type it was stored as (`<f4`, `|b1`, ...).
    pub dtype: String,
    pub values: Values,
}

impl Array {
    /// The values as f64 (bools as 0 and 1), or `None` for objects.
    pub fn to_f64(&self) -> Option<Vec<f64>> {
        match &self.values {
            Values::Bool(v) => Some(v.iter().map(|&b| b as u8 as f64).collect()),
            Values::Int(v) => Some(v.iter().map(|&i| i as f64).collect()),
            Values::Float(v) => Some(v.clone()),
            Values::Object(_) => None,
        }
    }

    /// The values as bools (numbers: non-zero), or `None` for objects.
    pub fn to_bool(&self) -> Option<Vec<bool>> {
        match &self.values {
            Values::Bool(v) => Some(v.clone()),
            Values::Int(v) => Some(v.iter().map(|&i| i != 0).collect()),
            Values::Float(v) => Some(v.iter().map(|&f| f != 0.0).collect()),
            Values::Object(_) => None,
        }
    }
}

/// The arrays of an archive by name (the member's name without `.npy`).
pub type Npz = BTreeMap<String, Array>;

/// Reads the archive at `path`.
pub fn read(path: &Path) -> Result<Npz> {
    let bytes = std::fs::read(path).map_err(|e| read_error(path, e))?;
    from_bytes(&bytes).map_err(|why| content_error(path, format!("not a numpy .npz archive: {why}")))
}

fn u16_at(b: &[u8], at: usize) -> std::result::Result<u16, String> {
    b.get(at..at + 2).map(|s| u16::from_le_bytes([s[0], s[1]])).ok_or_else(|| "cut short".into())
}

fn u32_at(b: &[u8], at: usize) -> std::result::Result<u32, String> {
    b.get(at..at + 4)
        .map(|s| u32::from_le_bytes(s.try_into().expect("4 bytes")))
        .ok_or_else(|| "cut short".into())
}

fn u64_at(b: &[u8], at: usize) -> std::result::Result<u64, String> {
    b.get(at..at + 8)
        .map(|s| u64::from_le_bytes(s.try_into().expect("8 bytes")))
        .ok_or_else(|| "cut short".into())
}

/// A member of the central directory: its name, method, sizes and local header's offset.
struct Entry {
    name: String,
    method: u16,
    compressed: u64,
    size: u64,
    offset: u64,
}

/// The sizes and offset a zip64 extra field (id 1) holds in place of those set to all ones.
fn zip64(extra: &[u8], e: &mut Entry, want: [bool; 3]) -> std::result::Result<(), String> {
    let mut at = 0;
    while at + 4 <= extra.len() {
        let (id, len) = (u16_at(extra, at)?, u16_at(extra, at + 2)? as usize);
        let field = extra.get(at + 4..at + 4 + len).ok_or("a zip64 field cut short")?;
        if id == 1 {
            let mut k = 0;
            for (i, slot) in [&mut e.size, &mut e.compressed, &mut e.offset].into_iter().enumerate() {
                if want[i] {
                    *slot = u64_at(field, k)?;
                    k += 8;
                }
            }
            return Ok(());
        }
        at += 4 + len;
    }
    if want.iter().any(|&w| w) {
        return Err(format!("{}: sizes past 4 GB without a zip64 field", e.name));
    }
    Ok(())
}

/// The members the central directory lists.
fn entries(b: &[u8]) -> std::result::Result<Vec<Entry>, String> {
    // The end of central directory record: 22 bytes and a comment of up to 64 KiB.
    let lo = b.len().saturating_sub(22 + 65535);
    let eocd = (lo..b.len().saturating_sub(21))
        .rev()
        .find(|&i| b[i..i + 4] == [0x50, 0x4b, 0x05, 0x06])
        .ok_or("no end of central directory (not a zip archive)")?;
    let mut count = u16_at(b, eocd + 10)? as u64;
    let mut start = u32_at(b, eocd + 16)? as u64;
    if (count == 0xffff || start == 0xffff_ffff)
        && eocd >= 20
        && b[eocd - 20..eocd - 16] == [0x50, 0x4b, 0x06, 0x07]
    {
        let record = u64_at(b, eocd - 12)? as usize;
        if b.get(record..record + 4) != Some(&[0x50, 0x4b, 0x06, 0x06]) {
            return Err("a zip64 locator that points at no zip64 record".into());
        }
        count = u64_at(b, record + 32)?;
        start = u64_at(b, record + 48)?;
    }
    let mut at = start as usize;
    let mut out = Vec::new();
    for _ in 0..count {
        if u32_at(b, at)? != 0x0201_4b50 {
            return Err("a central directory entry without its signature".into());
        }
        let method = u16_at(b, at + 10)?;
        let compressed = u32_at(b, at + 20)?;
        let size = u32_at(b, at + 24)?;
        let (name_len, extra_len, comment_len) =
            (u16_at(b, at + 28)? as usize, u16_at(b, at + 30)? as usize, u16_at(b, at + 32)? as usize);
        let offset = u32_at(b, at + 42)?;
        let name = b.get(at + 46..at + 46 + name_len).ok_or("a member name cut short")?;
        let name = String::from_utf8_lossy(name).into_owned();
        let extra =
            b.get(at + 46 + name_len..at + 46 + name_len + extra_len).ok_or("an extra field cut short")?;
        let mut e =
            Entry { name, method, compressed: compressed as u64, size: size as u64, offset: offset as u64 };
        let all = u32::MAX;
        zip64(extra, &mut e, [size == all, compressed == all, offset == all])?;
        out.push(e);
        at += 46 + name_len + extra_len + comment_len;
    }
    Ok(out)
}

/// A member's bytes, inflated.
fn member(b: &[u8], e: &Entry) -> std::result::Result<Vec<u8>, String> {
    let at = e.offset as usize;
    if u32_at(b, at)? != 0x0403_4b50 {
        return Err(format!("{}: no local header where the directory says", e.name));
    }
    let data = at + 30 + u16_at(b, at + 26)? as usize + u16_at(b, at + 28)? as usize;
    let raw = b.get(data..data + e.compressed as usize).ok_or_else(|| format!("{}: cut short", e.name))?;
    let out = match e.method {
        0 => raw.to_vec(),
        8 => {
            let mut out = Vec::with_capacity(e.size as usize);
            flate2::read::DeflateDecoder::new(raw)
                .read_to_end(&mut out)
                .map_err(|err| format!("{}: {err}", e.name))?;
            out
        }
        m => {
            return Err(format!(
                "{}: compression method {m} (numpy writes stored or deflated members)",
                e.name
            ))
        }
    };
    if out.len() as u64 != e.size {
        return Err(format!("{}: {} bytes where the directory says {}", e.name, out.len(), e.size));
    }
    Ok(out)
}

/// The arrays of an archive's bytes.
pub fn from_bytes(b: &[u8]) -> std::result::Result<Npz, String> {
    let mut out = Npz::new();
    for e in entries(b)? {
        let Some(name) = e.name.strip_suffix(".npy") else { continue };
        let bytes = member(b, &e)?;
        out.insert(name.to_string(), parse_npy(&bytes).map_err(|why| format!("{}: {why}", e.name))?);
    }
    Ok(out)
}

/// The value of `key` in the header dict `{'descr': '<f4', 'fortran_order': False, 'shape':
/// (2, 3), }`, as its text.
fn header_value<'a>(header: &'a str, key: &str) -> std::result::Result<&'a str, String> {
    let at = header.find(&format!("'{key}'")).ok_or_else(|| format!("the header has no {key}"))?;
    let rest =
        header[at + key.len() + 2..].trim_start().strip_prefix(':').ok_or("a malformed header")?.trim_start();
    let end = if rest.starts_with('(') { rest.find(')').map(|i| i + 1) } else { rest.find([',', '}']) };
    Ok(rest[..end.ok_or("a malformed header")?].trim())
}

/// One `.npy` file.
pub fn parse_npy(b: &[u8]) -> std::result::Result<Array, String> {
    if b.len() < 10 || &b[..6] != b"\x93NUMPY" {
        return Err("not an .npy array (no \\x93NUMPY magic)".into());
    }
    let (len, start) = match b[6] {
        1 => (u16_at(b, 8)? as usize, 10),
        2 | 3 => (u32_at(b, 8)? as usize, 12),
        v => return Err(format!("npy format version {v}")),
    };
    let header = std::str::from_utf8(b.get(start..start + len).ok_or("a header cut short")?)
        .map_err(|_| "a header that is not text")?;
    let descr = header_value(header, "descr")?.trim_matches(['\'', '"']).to_string();
    if header_value(header, "fortran_order")? != "False" {
        return Err("a Fortran-order array (save it in C order)".into());
    }
    let shape_text = header_value(header, "shape")?;
    let shape: Vec<usize> = shape_text
        .trim_matches(['(', ')'])
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| format!("shape {shape_text}")))
        .collect::<std::result::Result<_, _>>()?;
    let n: usize = shape.iter().product();
    let body = &b[start + len..];
    let values = if descr == "|O" {
        Values::Object(body.to_vec())
    } else {
        let width = match &descr[1..] {
            "b1" | "u1" | "i1" => 1,
            "u2" | "i2" | "f2" => 2,
            "u4" | "i4" | "f4" => 4,
            "u8" | "i8" | "f8" => 8,
            other => return Err(format!("dtype {descr} ({other}) is not a bool, integer or float")),
        };
        if width > 1 && !descr.starts_with('<') {
            return Err(format!("dtype {descr} is not little-endian"));
        }
        let body =
            body.get(..n * width).ok_or_else(|| format!("{} bytes for {n} values of {descr}", body.len()))?;
        let words = body.chunks_exact(width);
        match &descr[1..] {
            "b1" => Values::Bool(body.iter().map(|&x| x != 0).collect()),
            "u1" => Values::Int(body.iter().map(|&x| x as i64).collect()),
            "i1" => Values::Int(body.iter().map(|&x| x as i8 as i64).collect()),
            "u2" => Values::Int(words.map(|w| u16::from_le_bytes([w[0], w[1]]) as i64).collect()),
            "i2" => Values::Int(words.map(|w| i16::from_le_bytes([w[0], w[1]]) as i64).collect()),
            "u4" => Values::Int(words.map(|w| u32::from_le_bytes(w.try_into().unwrap()) as i64).collect()),
            "i4" => Values::Int(words.map(|w| i32::from_le_bytes(w.try_into().unwrap()) as i64).collect()),
            "i8" | "u8" => Values::Int(words.map(|w| i64::from_le_bytes(w.try_into().unwrap())).collect()),
            "f2" => Values::Float(words.map(|w| half_to_f64(u16::from_le_bytes([w[0], w[1]]))).collect()),
            "f4" => Values::Float(words.map(|w| f32::from_le_bytes(w.try_into().unwrap()) as f64).collect()),
            _ => Values::Float(words.map(|w| f64::from_le_bytes(w.try_into().unwrap())).collect()),
        }
    };
    Ok(Array { shape, dtype: descr, values })
}

/// An IEEE half's value.
fn half_to_f64(h: u16) -> f64 {
    let (sign, exp, frac) = ((h >> 15) as i32, ((h >> 10) & 0x1f) as i32, (h & 0x3ff) as f64);
    let v = match exp {
        0 => frac * 2f64.powi(-24),
        31 if frac == 0.0 => f64::INFINITY,
        31 => f64::NAN,
        e => (1.0 + frac / 1024.0) * 2f64.powi(e - 15),
    };
    if sign == 1 {
        -v
    } else {
        v
    }
}

/// The (width, height) of the first JPEG image among `bytes` (a pickled array of JPEG files:
/// TAPVid-3D's `images_jpeg_bytes`), read from its frame header.
pub fn first_jpeg_size(bytes: &[u8]) -> Option<(u32, u32)> {
    let start = bytes.windows(3).position(|w| w == [0xff, 0xd8, 0xff])?;
    let mut at = start + 2;
    while at + 4 <= bytes.len() {
        if bytes[at] != 0xff {
            return None;
        }
        let marker = bytes[at + 1];
        let len = u16::from_be_bytes([bytes[at + 2], bytes[at + 3]]) as usize;
        // SOF0..SOF15 but DHT (C4), JPG (C8) and DAC (CC): the frame header.
        if (0xc0..=0xcf).contains(&marker) && ![0xc4, 0xc8, 0xcc].contains(&marker) {
            let h = u16::from_be_bytes([*bytes.get(at + 5)?, *bytes.get(at + 6)?]) as u32;
            let w = u16::from_be_bytes([*bytes.get(at + 7)?, *bytes.get(at + 8)?]) as u32;
            return Some((w, h));
        }
        at += 2 + len;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn npy(descr: &str, fortran: &str, shape: &str, body: &[u8]) -> Vec<u8> {
        let header = format!("{{'descr': '{descr}', 'fortran_order': {fortran}, 'shape': {shape}, }}");
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(body);
        out
    }

    #[test]
    fn arrays_of_numbers_parse_and_other_layouts_are_refused() {
        let body: Vec<u8> =
            [1.5f32, -2.0, 0.25, 8.0, 0.0, 3.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let a = parse_npy(&npy("<f4", "False", "(2, 3)", &body)).unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.to_f64().unwrap(), vec![1.5, -2.0, 0.25, 8.0, 0.0, 3.0]);
        let b = parse_npy(&npy("|b1", "False", "(3,)", &[1, 0, 1])).unwrap();
        assert_eq!(b.to_bool().unwrap(), vec![true, false, true]);
        let e = parse_npy(&npy("<f2", "False", "()", &0x3c00u16.to_le_bytes())).unwrap();
        assert_eq!((e.shape.len(), e.to_f64().unwrap()), (0, vec![1.0]));
        assert!(parse_npy(&npy("<f4", "True", "(2, 3)", &body)).unwrap_err().contains("Fortran"));
        assert!(parse_npy(&npy(">f4", "False", "(2, 3)", &body)).unwrap_err().contains("little-endian"));
        assert!(parse_npy(&npy("<f4", "False", "(4, 3)", &body)).unwrap_err().contains("24 bytes for 12"));
        assert!(parse_npy(&npy("<c8", "False", "(1,)", &body)).unwrap_err().contains("c8"));
        assert!(from_bytes(b"not a zip").unwrap_err().contains("end of central directory"));
    }

    #[test]
    fn the_size_of_a_jpeg_is_its_frame_headers() {
        let mut jpeg = vec![0x80, 0x03, 0xff, 0xd8, 0xff, 0xe0, 0x00, 0x04, 0x00, 0x00];
        jpeg.extend_from_slice(&[0xff, 0xc2, 0x00, 0x11, 0x08, 0x01, 0xe0, 0x02, 0x80, 0x03]);
        assert_eq!(first_jpeg_size(&jpeg), Some((640, 480)));
        assert_eq!(first_jpeg_size(b"no image here"), None);
    }
}
