//! The bytes of a glTF asset: the JSON (of a `.gltf`, or the JSON chunk of a `.glb`), its
//! buffers and its images.
//!
//! A URI is read only when it is a `data:` URI in base64 or a relative path that stays inside
//! the glTF file's folder: percent-decoded, never absolute, never climbing out with `..`, and
//! canonicalised so that a symbolic link cannot lead out either. Any other URI is refused with
//! its text. A GLB's first buffer may be its BIN chunk. Images are PNG or JPEG, from a URI or a
//! buffer view.

use std::io::Read;
use std::path::{Component, Path, PathBuf};

use gltf::json::Root;

/// Largest image file read (its decoded size is bounded by the `image` crate's limits).
pub const MAX_IMAGE_BYTES: u64 = 256 << 20;

const GLB_MAGIC: &[u8; 4] = b"glTF";
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;

fn u32_at(bytes: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_le_bytes(bytes.get(at..at.checked_add(4)?)?.try_into().ok()?))
}

/// Splits a file into its JSON document and, for a GLB, its BIN chunk (spec 4.4).
pub fn parse(bytes: &[u8]) -> Result<(Root, Option<Vec<u8>>), String> {
    let (json_bytes, bin) = if bytes.starts_with(GLB_MAGIC) { glb_chunks(bytes)? } else { (bytes, None) };
    let root: Root =
        serde_json::from_slice(json_bytes).map_err(|e| format!("not a readable glTF 2.0 file: {e}"))?;
    Ok((root, bin.map(<[u8]>::to_vec)))
}

fn glb_chunks(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), String> {
    let version = u32_at(bytes, 4).ok_or("a GLB header of fewer than 12 bytes")?;
    if version != 2 {
        return Err(format!("GLB version {version}: only glTF 2.0 is read"));
    }
    let length = u32_at(bytes, 8).ok_or("a GLB header of fewer than 12 bytes")? as usize;
    if length > bytes.len() || length < 12 {
        return Err(format!("the GLB header says {length} bytes, the file has {}", bytes.len()));
    }
    let bytes = &bytes[..length];
    let mut at = 12;
    let (mut json, mut bin) = (None, None);
    while at < bytes.len() {
        let (len, kind) = match (u32_at(bytes, at), u32_at(bytes, at + 4)) {
            (Some(len), Some(kind)) => (len as usize, kind),
            _ => return Err(format!("GLB chunk header at byte {at} runs past the end of the file")),
        };
        let start = at + 8;
        let data = start.checked_add(len).and_then(|end| bytes.get(start..end)).ok_or_else(|| {
            format!("GLB chunk at byte {at} declares {len} bytes, past the end of the file")
        })?;
        match kind {
            CHUNK_JSON if json.is_none() && at == 12 => json = Some(data),
            CHUNK_BIN if bin.is_none() && json.is_some() => bin = Some(data),
            CHUNK_JSON | CHUNK_BIN => {
                return Err(format!("GLB chunk at byte {at} is out of order or repeated"))
            }
            _ => {} // chunks of extensions: skipped, as the specification says
        }
        at = start + len;
    }
    Ok((json.ok_or("the GLB has no JSON chunk")?, bin))
}

/// Loads every buffer of the document: `bin` is a GLB's BIN chunk, `dir` the glTF file's
/// folder. Each buffer holds at least its byteLength bytes.
pub fn buffers(root: &Root, mut bin: Option<Vec<u8>>, dir: &Path) -> Result<Vec<Vec<u8>>, String> {
    let mut out = Vec::with_capacity(root.buffers.len());
    for (i, b) in root.buffers.iter().enumerate() {
        let at = format!("buffers[{i}]");
        let need = b.byte_length.0;
        let bytes = match &b.uri {
            None if i == 0 => {
                bin.take().ok_or_else(|| format!("{at} has no uri and the file has no GLB BIN chunk"))?
            }
            None => return Err(format!("{at} has no uri (only a GLB's first buffer is its BIN chunk)")),
            Some(uri) => read_uri(uri, dir, need, &at)?,
        };
        if (bytes.len() as u64) < need {
            return Err(format!("{at}: byteLength {need}, but its data has {} bytes", bytes.len()));
        }
        out.push(bytes);
    }
    Ok(out)
}

/// Decodes image `index` (PNG or JPEG) from its URI or buffer view.
pub fn image(
    root: &Root,
    index: usize,
    buffers: &[Vec<u8>],
    dir: &Path,
) -> Result<image::DynamicImage, String> {
    let img = &root.images[index];
    let at = format!("images[{index}]");
    let mut mime = img.mime_type.as_ref().map(|m| m.0.clone());
    let bytes: Vec<u8> = match (&img.uri, img.buffer_view) {
        (Some(uri), _) => {
            if let Some(media) = uri.strip_prefix("data:").and_then(|r| r.split([';', ',']).next()) {
                mime = mime.or_else(|| Some(media.to_string()));
            }
            read_uri(uri, dir, MAX_IMAGE_BYTES, &at)?
        }
        (None, Some(v)) => {
            // Inside the buffer: checked by gltf_validate.
            let view = &root.buffer_views[v.value()];
            let start = view.byte_offset.map_or(0, |o| o.0) as usize;
            buffers[view.buffer.value()][start..start + view.byte_length.0 as usize].to_vec()
        }
        (None, None) => return Err(format!("{at} has neither a uri nor a bufferView")),
    };
    let format = match mime.as_deref() {
        Some("image/png") => image::ImageFormat::Png,
        Some("image/jpeg") => image::ImageFormat::Jpeg,
        _ => match image::guess_format(&bytes) {
            Ok(f @ (image::ImageFormat::Png | image::ImageFormat::Jpeg)) => f,
            _ => return Err(format!("{at} is neither PNG nor JPEG")),
        },
    };
    image::load_from_memory_with_format(&bytes, format).map_err(|e| format!("{at}: {e}"))
}

/// Reads up to `limit` bytes that `uri` names (see the module docs). `at` names the object
/// for errors.
fn read_uri(uri: &str, dir: &Path, limit: u64, at: &str) -> Result<Vec<u8>, String> {
    let shown: String = match uri.char_indices().nth(80) {
        Some((cut, _)) => format!("{}...", &uri[..cut]),
        None => uri.into(),
    };
    if let Some(rest) = uri.strip_prefix("data:") {
        let (header, payload) =
            rest.split_once(',').ok_or_else(|| format!("{at}: data URI {shown} has no comma"))?;
        if !header.ends_with(";base64") {
            return Err(format!("{at}: data URI {shown} is not base64"));
        }
        return base64(payload).map_err(|why| format!("{at}: data URI {shown}: {why}"));
    }
    let scheme = uri.split_once(':').map(|(s, _)| s).filter(|s| {
        s.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
            && s.chars().all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c))
    });
    if let Some(scheme) = scheme {
        return Err(format!(
            "{at}: URI {shown} has the scheme {scheme}: only data: URIs and relative paths inside the glTF file's folder are read"
        ));
    }
    let decoded = percent_decode(uri).map_err(|why| format!("{at}: URI {shown}: {why}"))?;
    let relative = Path::new(&decoded);
    let mut depth = 0usize;
    for c in relative.components() {
        match c {
            Component::Normal(_) => depth += 1,
            Component::CurDir => {}
            Component::ParentDir if depth > 0 => depth -= 1,
            Component::ParentDir => {
                return Err(format!("{at}: URI {shown} climbs out of the glTF file's folder"));
            }
            Component::RootDir | Component::Prefix(_) => {
                return Err(format!("{at}: URI {shown} is an absolute path; only paths inside the glTF file's folder are read"));
            }
        }
    }
    let folder = dir.canonicalize().map_err(|e| format!("{at}: the folder {}: {e}", dir.display()))?;
    let target: PathBuf = folder.join(relative);
    let real = target.canonicalize().map_err(|e| format!("{at}: cannot read {}: {e}", target.display()))?;
    if !real.starts_with(&folder) {
        return Err(format!(
            "{at}: URI {shown} leads to {}, outside the glTF file's folder {} (through a symbolic link)",
            real.display(),
            folder.display()
        ));
    }
    let file =
        std::fs::File::open(&real).map_err(|e| format!("{at}: cannot read {}: {e}", real.display()))?;
    let meta = file.metadata().map_err(|e| format!("{at}: cannot read {}: {e}", real.display()))?;
    if !meta.is_file() {
        return Err(format!("{at}: {} is not a file", real.display()));
    }
    let mut bytes = Vec::new();
    file.take(limit)
        .read_to_end(&mut bytes)
        .map_err(|e| format!("{at}: cannot read {}: {e}", real.display()))?;
    Ok(bytes)
}

/// Decodes `%XX` escapes (RFC 3986); the result must be UTF-8.
fn percent_decode(s: &str) -> Result<String, String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = b.get(i + 1..i + 3).and_then(|h| std::str::from_utf8(h).ok());
            let v = hex
                .and_then(|h| u8::from_str_radix(h, 16).ok())
                .ok_or("a % not followed by two hex digits")?;
            out.push(v);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).map_err(|_| "the decoded path is not UTF-8".into())
}

/// Decodes standard base64 (RFC 4648, `+` and `/`, padding optional).
pub fn base64(s: &str) -> Result<Vec<u8>, String> {
    let s = s.trim_end_matches('=');
    let mut out = Vec::with_capacity(s.len() / 4 * 3 + 2);
    let (mut acc, mut bits) = (0u32, 0u32);
    for (i, c) in s.bytes().enumerate() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            _ => return Err(format!("byte {i} of the base64 data is {:?}", c as char)),
        };
        acc = (acc << 6) | v as u32;
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    if bits >= 6 {
        return Err("the base64 data has a dangling character".into());
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_and_percent_decoding() {
        assert_eq!(base64("aGVsbG8=").unwrap(), b"hello");
        assert_eq!(base64("aGVsbG8").unwrap(), b"hello");
        assert_eq!(base64("").unwrap(), b"");
        assert_eq!(base64("AAECAwQF").unwrap(), [0, 1, 2, 3, 4, 5]);
        assert!(base64("aGV$bG8=").unwrap_err().contains("byte 3"));
        assert!(base64("aGVsb").is_err());
        assert_eq!(percent_decode("a%20b%2Fc.bin").unwrap(), "a b/c.bin");
        assert!(percent_decode("a%2").is_err());
        assert!(percent_decode("%ff").is_err());
    }
}
