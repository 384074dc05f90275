//! Hostile input for every reader of files: seeded mutations of real files (the glTF exports in
//! tests/fixtures/gltf, a GLB made from one of them) and of files the project writes (a scene
//! from the data pipeline, Gaussians as PLY, a checkpoint, a config, a scene's stored tokens
//! and a token folder's manifest): truncation at many
//! lengths, byte flips, extreme words, huge or negative counts in PLY headers and JSON, NaN and
//! Inf in float fields, property types and JSON types swapped. Each case must end in an error
//! that names the file or in a valid result (finite values, consistent counts), never in a
//! panic: every call runs under catch_unwind and a failing case is printed with what was done
//! to the file. `--nocapture` shows the cases per reader and the time.

use crate::common;
use common::*;
use velox_models::Model;

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde_json::{json, Value};
use velox::data::format::{read_ply, read_scene, write_scene};
use velox::data::gltf_import::import;
use velox::data::procedural::scene;
use velox::data::SynthOptions;
use velox::engine::ops::raster::GaussianData;
use velox::io::ply;
use velox::models::checkpoint;
use velox::models::config::AutoencoderConfig;
use velox::models::params::{Init, ParamStore};
use velox::models::velox::autoencoder::Autoencoder;
use velox::models::velox::tokens::{
    read_scene_file, write_scene_file, CheckpointCheck, SceneTokens, TokenFolder, TokenManifest, TokenOrigin,
    TokenStats, MANIFEST,
};

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("velox-fuzz-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Counts the cases of one reader and collects the failures.
struct Fuzz {
    reader: &'static str,
    cases: usize,
    failures: Vec<String>,
    start: Instant,
}

impl Fuzz {
    fn new(reader: &'static str) -> Fuzz {
        Fuzz { reader, cases: 0, failures: Vec::new(), start: Instant::now() }
    }

    /// Runs one case; `run` says why its outcome is not acceptable, or panics.
    fn case(&mut self, what: &str, run: impl FnOnce() -> Result<(), String>) {
        self.cases += 1;
        let failure = match catch_unwind(AssertUnwindSafe(run)) {
            Ok(Ok(())) => return,
            Ok(Err(why)) => why,
            Err(payload) => {
                let msg = payload
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| payload.downcast_ref::<String>().cloned())
                    .unwrap_or_default();
                format!("PANIC: {msg}")
            }
        };
        let line = format!("{} case {} ({what}): {failure}", self.reader, self.cases);
        eprintln!("{line}");
        self.failures.push(line);
    }

    fn finish(self) {
        let secs = self.start.elapsed().as_secs_f64();
        eprintln!("fuzz {}: {} cases in {secs:.1} s", self.reader, self.cases);
        assert!(
            self.failures.is_empty(),
            "{} of {} {} cases failed:\n{}",
            self.failures.len(),
            self.cases,
            self.reader,
            self.failures.join("\n")
        );
    }
}

/// An error is acceptable when it names `file` and no panic was turned into it; a result when
/// `valid` accepts it.
fn named_or_valid<T, E: std::fmt::Display>(
    result: Result<T, E>,
    file: &Path,
    valid: impl FnOnce(T) -> Result<(), String>,
) -> Result<(), String> {
    match result {
        Ok(v) => valid(v),
        Err(e) => {
            let e = e.to_string();
            let name = file.file_name().unwrap().to_string_lossy();
            if !e.contains(&*name) {
                Err(format!("the error does not name {name}: {e}"))
            } else if e.contains("panicked") {
                Err(format!("a panic became this error: {e}"))
            } else {
                Ok(())
            }
        }
    }
}

fn all_finite(what: &str, values: &[f32]) -> Result<(), String> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(format!("accepted, but {what}[{i}] is {}", values[i])),
        None => Ok(()),
    }
}

/// Extreme 32-bit words: counts and lengths at their limits, NaN and infinities.
const WORDS: [u32; 9] =
    [0, 1, 0x7fff_ffff, 0x8000_0000, 0xffff_ffff, 0x7fc0_0000, 0x7f80_0000, 0xff80_0000, 0x4000_0000];

/// Seeded mutations of a binary file: truncations (every length up to 64 and `n` more),
/// `n` sets of bit flips, `n` extreme words at random offsets, `n / 4` random splices.
fn byte_mutations(rng: &mut Rng, bytes: &[u8], n: usize) -> Vec<(String, Vec<u8>)> {
    let len = bytes.len() as u32;
    let mut out = Vec::new();
    let lengths: Vec<usize> =
        (0..bytes.len().min(64)).chain((0..n).map(|_| rng.below(len) as usize)).collect();
    for l in lengths {
        out.push((format!("truncated to {l} bytes"), bytes[..l].to_vec()));
    }
    for _ in 0..n {
        let mut b = bytes.to_vec();
        let flips: Vec<(usize, u32)> =
            (0..1 + rng.below(4)).map(|_| (rng.below(len) as usize, rng.below(8))).collect();
        for &(at, bit) in &flips {
            b[at] ^= 1 << bit;
        }
        out.push((format!("bits flipped at {flips:?}"), b));
    }
    for _ in 0..n {
        let mut b = bytes.to_vec();
        let at = rng.below(len.saturating_sub(4).max(1)) as usize;
        let w = WORDS[rng.below(WORDS.len() as u32) as usize];
        let end = (at + 4).min(b.len());
        b[at..end].copy_from_slice(&w.to_le_bytes()[..end - at]);
        out.push((format!("word {w:#x} at byte {at}"), b));
    }
    for _ in 0..n / 4 {
        let (a, b) = (rng.below(len) as usize, rng.below(len) as usize);
        let (a, b) = (a.min(b), a.max(b));
        let mut v = bytes[..a].to_vec();
        v.extend_from_slice(&bytes[b..]);
        v.extend_from_slice(&bytes[a..b]);
        out.push((format!("bytes {a}..{b} moved to the end"), v));
    }
    out
}

/// Every 4-byte float slot `slots` (byte offsets) set to NaN, Inf and -Inf in turn.
fn float_mutations(bytes: &[u8], slots: impl IntoIterator<Item = usize>) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for at in slots {
        for x in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut b = bytes.to_vec();
            b[at..at + 4].copy_from_slice(&x.to_le_bytes());
            out.push((format!("{x} at byte {at}"), b));
        }
    }
    out
}

/// Counts for PLY headers and JSON: zero, off by one, past 32 and 64 bits, negative, not a
/// number. Written as text: 1e309 is past f64 and 1e39 past f32.
const COUNTS: [&str; 11] = [
    "0",
    "1",
    "4294967296",
    "1000000000000000000",
    "18446744073709551615",
    "18446744073709551616",
    "-1",
    "1e39",
    "1e309",
    "-1e39",
    "2.5",
];

/// Mutations of a PLY header: every element count replaced by each of [`COUNTS`] and by its
/// neighbours, every property's type swapped, removed or doubled, the format changed.
fn ply_header_mutations(bytes: &[u8]) -> Vec<(String, Vec<u8>)> {
    let end = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let header = std::str::from_utf8(&bytes[..end]).unwrap();
    let body = &bytes[end..];
    let lines: Vec<&str> = header.lines().collect();
    let mut out = Vec::new();
    let with = |i: usize, new: Option<String>, dup: bool| {
        let mut ls: Vec<String> = lines.iter().map(|l| l.to_string()).collect();
        match new {
            Some(n) if dup => ls.insert(i, n),
            Some(n) => ls[i] = n,
            None => drop(ls.remove(i)),
        }
        let mut b = (ls.join("\n") + "\n").into_bytes();
        b.extend_from_slice(body);
        b
    };
    for (i, line) in lines.iter().enumerate() {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["element", name, count] => {
                let n: i128 = count.parse().unwrap();
                let near = [(n - 1).to_string(), (n + 1).to_string(), (2 * n).to_string()];
                for c in COUNTS.iter().map(|c| c.to_string()).chain(near) {
                    out.push((
                        format!("element {name} {c}"),
                        with(i, Some(format!("element {name} {c}")), false),
                    ));
                }
            }
            ["property", ty, name] => {
                for new in ["uchar", "double", "int", "short", "list uchar int", "half"] {
                    let desc = format!("property {name}: {ty} -> {new}");
                    out.push((desc, with(i, Some(format!("property {new} {name}")), false)));
                }
                out.push((format!("property {name} removed"), with(i, None, false)));
                out.push((format!("property {name} doubled"), with(i, Some(line.to_string()), true)));
            }
            ["format", ..] => {
                for f in ["ascii 1.0", "binary_big_endian 1.0", "binary_little_endian"] {
                    out.push((format!("format {f}"), with(i, Some(format!("format {f}")), false)));
                }
                out.push(("format line removed".into(), with(i, None, false)));
            }
            _ => {}
        }
    }
    out
}

/// The JSON pointers of every leaf (number, string, bool, null) of `v`.
fn leaves(v: &Value, at: String, out: &mut Vec<String>) {
    match v {
        Value::Object(o) => o.iter().for_each(|(k, v)| {
            // JSON pointers escape `~` and `/` in keys (RFC 6901).
            leaves(v, format!("{at}/{}", k.replace('~', "~0").replace('/', "~1")), out)
        }),
        Value::Array(a) => a.iter().enumerate().for_each(|(i, v)| leaves(v, format!("{at}/{i}"), out)),
        _ => out.push(at),
    }
}

/// Mutations of a JSON document: at `max_leaves` leaves (all if there are fewer, else a
/// seeded sample), the leaf replaced by each of [`COUNTS`], a string, null, an empty array;
/// a sample of keys removed and of arrays emptied.
fn json_mutations(rng: &mut Rng, text: &str, max_leaves: usize) -> Vec<(String, String)> {
    let root: Value = serde_json::from_str(text).unwrap();
    let mut all = Vec::new();
    leaves(&root, String::new(), &mut all);
    let picked: Vec<&String> = if all.len() <= max_leaves {
        all.iter().collect()
    } else {
        (0..max_leaves).map(|_| &all[rng.below(all.len() as u32) as usize]).collect()
    };
    let mut out = Vec::new();
    const MARK: &str = "\"@@replaced@@\"";
    for at in picked {
        let replace = |text: &str| {
            let mut v = root.clone();
            *v.pointer_mut(at).unwrap() = Value::String("@@replaced@@".into());
            v.to_string().replace(MARK, text)
        };
        for c in COUNTS.iter().chain(&["\"text\"", "null", "[]", "true"]) {
            out.push((format!("{at} = {c}"), replace(c)));
        }
        // The parent without this key, or the array without this element.
        let (parent, key) = at.rsplit_once('/').unwrap();
        let mut v = root.clone();
        match v.pointer_mut(parent) {
            Some(Value::Object(o)) => drop(o.remove(&key.replace("~1", "/").replace("~0", "~"))),
            Some(Value::Array(a)) => drop(a.remove(key.parse::<usize>().unwrap())),
            _ => {}
        }
        out.push((format!("{at} removed"), v.to_string()));
    }
    out
}

#[test]
fn fuzz_point_cloud_ply() {
    let dir = temp_dir("cloud");
    let path = dir.join("points.ply");
    let points: Vec<[f32; 7]> = (0..40)
        .map(|i| {
            let x = i as f32 / 40.0;
            [x - 0.5, 0.3 - x, 0.1, x, 1.0 - x, 0.5, (i % 24) as f32 / 100.0]
        })
        .collect();
    velox::data::format::write_ply(&path, &points).unwrap();
    let good = std::fs::read(&path).unwrap();
    let body = good.len() - 40 * 28;
    let mut rng = Rng::new(0xc10d);
    let mut cases = byte_mutations(&mut rng, &good, 200);
    cases.extend(ply_header_mutations(&good));
    // NaN and Inf in every column, at the first, a middle and the last point.
    cases.extend(float_mutations(
        &good,
        [0, 17, 39].iter().flat_map(|p| (0..7).map(move |c| body + 28 * p + 4 * c)),
    ));
    let mut fuzz = Fuzz::new("point-cloud PLY (velox_data::format::read_ply)");
    for (what, bytes) in cases {
        std::fs::write(&path, &bytes).unwrap();
        fuzz.case(&what, || {
            named_or_valid(read_ply(&path), &path, |p| {
                let flat: Vec<f32> = p.iter().flatten().copied().collect();
                all_finite("points", &flat)?;
                if p.iter().any(|q| q[..3].iter().any(|x| x.abs() > 1.001) || q[6] < 0.0 || q[6] > 0.235) {
                    return Err("accepted a point outside the format's ranges".into());
                }
                Ok(())
            })
        });
    }
    fuzz.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn fuzz_gaussian_ply() {
    let dir = temp_dir("gaussians");
    let path = dir.join("gaussians.ply");
    let mut g = GaussianData::default();
    let mut rng = Rng::new(0x9a55);
    for i in 0..24 {
        let r = |rng: &mut Rng| rng.range(-1.0, 1.0) as f32;
        g.push(
            [r(&mut rng), r(&mut rng), r(&mut rng)],
            [-3.0; 3],
            [1.0, 0.0, 0.0, 0.0],
            i as f32 / 10.0,
            [0.5; 3],
        );
    }
    let good = ply::to_bytes(&g).unwrap();
    let body = good.len() - 24 * 17 * 4;
    let mut cases = byte_mutations(&mut rng, &good, 300);
    cases.extend(ply_header_mutations(&good));
    cases.extend(float_mutations(
        &good,
        [0, 23].iter().flat_map(|p| (0..17).map(move |c| body + 68 * p + 4 * c)),
    ));
    let mut fuzz = Fuzz::new("Gaussian PLY (velox_io::ply::read, from_bytes)");
    for (what, bytes) in cases {
        std::fs::write(&path, &bytes).unwrap();
        fuzz.case(&what, || {
            let from_bytes = ply::from_bytes(&bytes).map(|g| g.len()).map_err(|e| e.to_string());
            named_or_valid(ply::read(&path), &path, |g| {
                g.check().map_err(|e| format!("accepted inconsistent Gaussians: {e}"))?;
                for (name, v) in [
                    ("means", &g.means),
                    ("log_scales", &g.log_scales),
                    ("quats", &g.quats),
                    ("opacities", &g.opacities),
                    ("colours", &g.colours),
                ] {
                    all_finite(name, v)?;
                }
                if from_bytes != Ok(g.len()) {
                    return Err(format!("read gives {} Gaussians, from_bytes {from_bytes:?}", g.len()));
                }
                Ok(())
            })
        });
    }
    fuzz.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

/// A glTF file whose buffers are data: URIs, as one GLB with a BIN chunk.
fn to_glb(gltf: &str) -> Vec<u8> {
    let mut v: Value = serde_json::from_str(gltf).unwrap();
    let mut bin = Vec::new();
    let mut starts = Vec::new();
    for b in v["buffers"].as_array().unwrap() {
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        starts.push(bin.len());
        let uri = b["uri"].as_str().unwrap();
        bin.extend(velox::data::gltf_load::base64(uri.split_once(',').unwrap().1).unwrap());
    }
    for view in v["bufferViews"].as_array_mut().unwrap() {
        let start = starts[view["buffer"].as_u64().unwrap() as usize] as u64;
        view["byteOffset"] = (view["byteOffset"].as_u64().unwrap_or(0) + start).into();
        view["buffer"] = 0.into();
    }
    v["buffers"] = json!([{"byteLength": bin.len()}]);
    glb(&v.to_string(), &bin)
}

fn shared_gltf(name: &str) -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/gltf").join(name))
        .unwrap()
}

/// An import is valid when the mesh is: frames inside [-1, 1]^3, indices and textures in
/// range, texture coordinates finite.
fn valid_import(i: velox::data::gltf_import::Imported) -> Result<(), String> {
    i.mesh.validate().map_err(|e| format!("accepted an invalid mesh: {e}"))?;
    if i.mesh.frames.iter().flatten().flatten().any(|x| x.abs() > 1.0) {
        return Err("accepted a mesh outside [-1, 1]^3".into());
    }
    Ok(())
}

#[test]
fn fuzz_gltf_and_glb() {
    let dir = temp_dir("gltf");
    let skin = shared_gltf("SimpleSkin.gltf");
    let morph = shared_gltf("MorphStressTest.gltf");
    let skin_glb = to_glb(&skin);
    let mut rng = Rng::new(0x91f);
    let mut fuzz = Fuzz::new("glTF and GLB (velox_data::gltf_import::import)");
    let run = |fuzz: &mut Fuzz, name: &str, what: &str, bytes: &[u8]| {
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        fuzz.case(&format!("{name}: {what}"), || named_or_valid(import(&path, None), &path, valid_import));
    };
    // SimpleSkin as text: every JSON leaf (accessor counts, offsets, strides, indices...),
    // and the bytes themselves.
    for (what, text) in json_mutations(&mut rng, &skin, 400) {
        run(&mut fuzz, "skin.gltf", &what, text.as_bytes());
    }
    for (what, bytes) in byte_mutations(&mut rng, skin.as_bytes(), 150) {
        run(&mut fuzz, "skin.gltf", &what, &bytes);
    }
    // The same as a GLB: its header and chunk headers, its JSON chunk, NaN and Inf in its
    // binary chunk.
    let json_len = u32::from_le_bytes(skin_glb[12..16].try_into().unwrap()) as usize;
    let (json_chunk, bin_chunk) = (&skin_glb[20..20 + json_len], &skin_glb[28 + json_len..]);
    for at in [8, 12, 16, 20 + json_len, 24 + json_len] {
        for w in WORDS {
            let mut b = skin_glb.clone();
            b[at..at + 4].copy_from_slice(&w.to_le_bytes());
            run(&mut fuzz, "skin.glb", &format!("word {w:#x} at byte {at}"), &b);
        }
    }
    for (what, bytes) in byte_mutations(&mut rng, &skin_glb, 150) {
        run(&mut fuzz, "skin.glb", &what, &bytes);
    }
    let json_text = std::str::from_utf8(json_chunk).unwrap().trim_end();
    for (what, text) in json_mutations(&mut rng, json_text, 60) {
        run(&mut fuzz, "skin.glb", &format!("JSON chunk: {what}"), &glb(&text, bin_chunk));
    }
    for (what, bin) in float_mutations(bin_chunk, (0..bin_chunk.len() / 4).step_by(7).map(|k| 4 * k)) {
        run(&mut fuzz, "skin.glb", &format!("BIN chunk: {what}"), &glb(json_text, &bin));
    }
    // MorphStressTest, larger (one 563 KB buffer, textures): a sample of its JSON leaves and
    // bytes, and NaN and Inf in its morph targets.
    for (what, text) in json_mutations(&mut rng, &morph, 6) {
        run(&mut fuzz, "morph.gltf", &what, text.as_bytes());
    }
    for (what, bytes) in byte_mutations(&mut rng, morph.as_bytes(), 8) {
        run(&mut fuzz, "morph.gltf", &what, &bytes);
    }
    let morph_glb = to_glb(&morph);
    let json_len = u32::from_le_bytes(morph_glb[12..16].try_into().unwrap()) as usize;
    let (json_chunk, bin_chunk) = (&morph_glb[20..20 + json_len], &morph_glb[28 + json_len..]);
    let json_text = std::str::from_utf8(json_chunk).unwrap().trim_end();
    let slots: Vec<usize> = (0..10).map(|_| 4 * rng.below((bin_chunk.len() / 4) as u32) as usize).collect();
    for (what, bin) in float_mutations(bin_chunk, slots) {
        run(&mut fuzz, "morph.glb", &format!("BIN chunk: {what}"), &glb(json_text, &bin));
    }
    fuzz.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

/// A checkpoint's header: (length of the JSON, the JSON), and the data after it.
fn split_safetensors(bytes: &[u8]) -> (Value, &[u8]) {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    (serde_json::from_slice(&bytes[8..8 + n]).unwrap(), &bytes[8 + n..])
}

fn join_safetensors(header: &str, data: &[u8]) -> Vec<u8> {
    let mut out = (header.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

/// Mutations of a safetensors file `good`: 250 byte mutations; the header's length at 0, 1,
/// one off either way, `u64::MAX` and `extra_lengths`; mutations of the header's JSON (dtypes,
/// shapes, offsets, metadata); NaN and Inf at the start and the end of every tensor's data, and
/// with `middle` at one random place inside it.
fn safetensors_mutations(
    rng: &mut Rng,
    good: &[u8],
    extra_lengths: &[u64],
    middle: bool,
) -> Vec<(String, Vec<u8>)> {
    let (header, data) = split_safetensors(good);
    let header_text = header.to_string();
    let mut cases = byte_mutations(rng, good, 250);
    let len = header_text.len() as u64;
    let mut lengths = [&[0, 1, len - 1, len + 1, u64::MAX][..], extra_lengths].concat();
    lengths.sort_unstable();
    for n in lengths {
        let mut b = good.to_vec();
        b[..8].copy_from_slice(&n.to_le_bytes());
        cases.push((format!("header length {n}"), b));
    }
    for (what, text) in json_mutations(rng, &header_text, 200) {
        cases.push((format!("header: {what}"), join_safetensors(&text, data)));
    }
    let mut slots = Vec::new();
    for (name, t) in header.as_object().unwrap() {
        if name != "__metadata__" {
            let offsets = t["data_offsets"].as_array().unwrap();
            let (a, b) = (offsets[0].as_u64().unwrap() as usize, offsets[1].as_u64().unwrap() as usize);
            slots.push(a);
            if middle {
                slots.push(a + 4 * (rng.below(((b - a) / 4) as u32) as usize));
            }
            slots.push(b - 4);
        }
    }
    let data_start = good.len() - data.len();
    cases.extend(float_mutations(good, slots.iter().map(|s| data_start + s)));
    cases
}

#[test]
fn fuzz_checkpoints() {
    let gpu = gpu();
    let dir = temp_dir("checkpoint");
    let path = dir.join("ckpt.safetensors");
    let mut b = ParamStore::builder();
    b.add("enc.w", &[13, 7], Init::Xavier).unwrap();
    b.add("enc.b", &[13], Init::Zeros).unwrap();
    b.add("embed", &[3, 1, 4], Init::Normal { std: 0.02 }).unwrap();
    let mut store = b.build(&gpu, 1).unwrap();
    let config = json!({"model": "velox autoencoder", "config": AutoencoderConfig::tiny()}).to_string();
    checkpoint::save(&path, &store, &config).unwrap();
    let good = std::fs::read(&path).unwrap();
    let mut rng = Rng::new(0xc4e);
    // The header's length at its limits (7 and 2^32 - 1 too), NaN and Inf at each end of
    // every tensor's data.
    let cases = safetensors_mutations(&mut rng, &good, &[7, u32::MAX as u64], false);
    let mut fuzz = Fuzz::new("checkpoint (velox_models::checkpoint::load, peek)");
    for (what, bytes) in cases {
        std::fs::write(&path, &bytes).unwrap();
        fuzz.case(&what, || {
            named_or_valid(checkpoint::peek(&path), &path, |_| Ok(()))?;
            named_or_valid(Autoencoder::checkpoint_config(&path), &path, |c| {
                // A config is used once it validates; then every number in it is finite.
                if c.validate().is_ok() {
                    finite_json(&serde_json::to_value(&c).unwrap(), "")?;
                }
                Ok(())
            })?;
            named_or_valid(checkpoint::load(&path, &mut store), &path, |_| {
                let (m, v) = store.moments();
                all_finite("parameters", &store.flat_params().read::<f32>().unwrap())?;
                all_finite("first moments", &m.read::<f32>().unwrap())?;
                all_finite("second moments", &v.read::<f32>().unwrap())
            })
        });
    }
    fuzz.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

/// Every number of `v` finite and no null (serde writes NaN and Inf as null).
fn finite_json(v: &Value, at: &str) -> Result<(), String> {
    match v {
        Value::Null => Err(format!("accepted, but {at} is not a finite number")),
        Value::Number(n) if !n.as_f64().is_some_and(f64::is_finite) => {
            Err(format!("accepted, but {at} is {n}"))
        }
        Value::Object(o) => o.iter().try_for_each(|(k, v)| finite_json(v, &format!("{at}/{k}"))),
        Value::Array(a) => a.iter().enumerate().try_for_each(|(i, v)| finite_json(v, &format!("{at}/{i}"))),
        _ => Ok(()),
    }
}

#[test]
fn fuzz_config_json() {
    let dir = temp_dir("config");
    let path = dir.join("config.json");
    let good = serde_json::to_string_pretty(&AutoencoderConfig::tiny()).unwrap();
    let mut rng = Rng::new(0xc0f);
    let mut cases: Vec<(String, Vec<u8>)> =
        json_mutations(&mut rng, &good, 1000).into_iter().map(|(w, t)| (w, t.into_bytes())).collect();
    cases.extend(byte_mutations(&mut rng, good.as_bytes(), 200));
    let mut fuzz = Fuzz::new("config JSON (AutoencoderConfig::named, validate)");
    let arg = path.to_str().unwrap();
    for (what, bytes) in cases {
        std::fs::write(&path, &bytes).unwrap();
        fuzz.case(&what, || {
            named_or_valid(AutoencoderConfig::named(arg), &path, |c| {
                c.validate().map_err(|e| format!("named() returned a config that does not validate: {e}"))?;
                finite_json(&serde_json::to_value(&c).unwrap(), "")
            })
        });
    }
    fuzz.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn fuzz_scene_folders() {
    let root = temp_dir("scene");
    let dir = root.join("scene_00001");
    let (_, mesh) = scene(1, None).unwrap();
    let opts = SynthOptions { res: 16, points: 300, supersample: 1, tracks: 6, ..Default::default() };
    write_scene(&gpu(), &mesh, "procedural seed 1", None, 1, &opts, &dir, &mut |_| {}).unwrap();
    read_scene(&dir, true).unwrap();
    let mut rng = Rng::new(0x5ce);
    let mut cases: Vec<(&str, String, Vec<u8>)> = Vec::new();
    for file in ["meta.json", "cameras.json"] {
        let text = std::fs::read_to_string(dir.join(file)).unwrap();
        let leaves = if file == "meta.json" { 100 } else { 60 };
        for (what, t) in json_mutations(&mut rng, &text, leaves) {
            cases.push((file, what, t.into_bytes()));
        }
        for (what, b) in byte_mutations(&mut rng, text.as_bytes(), 30) {
            cases.push((file, what, b));
        }
    }
    let ply = std::fs::read(dir.join("points.ply")).unwrap();
    for (what, b) in ply_header_mutations(&ply).into_iter().chain(byte_mutations(&mut rng, &ply, 40)) {
        cases.push(("points.ply", what, b));
    }
    for file in ["occupancy.bin", "tracks.bin", "tracks_visibility.bin", "video/f03.png"] {
        let bytes = std::fs::read(dir.join(file)).unwrap();
        for (what, b) in byte_mutations(&mut rng, &bytes, 15) {
            cases.push((file, what, b));
        }
    }
    let tracks = std::fs::read(dir.join("tracks.bin")).unwrap();
    for (what, b) in float_mutations(&tracks, (0..tracks.len() / 4).step_by(29).map(|k| 4 * k)) {
        cases.push(("tracks.bin", what, b));
    }
    let mut fuzz = Fuzz::new("scene folder (velox_data::format::read_scene)");
    for (file, what, bytes) in cases {
        let original = std::fs::read(dir.join(file)).unwrap();
        std::fs::write(dir.join(file), &bytes).unwrap();
        // Images are read only when a PNG was changed.
        let images = file.ends_with(".png");
        fuzz.case(&format!("{file}: {what}"), || {
            named_or_valid(read_scene(&dir, images), &dir, |s| {
                let m = &s.meta;
                let counts = [
                    (s.points.len(), m.points),
                    (s.tracks.len(), m.tracks),
                    (s.visibility.len(), m.tracks),
                    (s.cameras.supervision.len(), m.supervision_views),
                ];
                if counts.iter().any(|(a, b)| a != b) || (images && s.video.len() != 24) {
                    return Err(format!("accepted a scene whose counts disagree: {counts:?}"));
                }
                all_finite("points", &s.points.iter().flatten().copied().collect::<Vec<f32>>())?;
                all_finite("tracks", &s.tracks.iter().flatten().flatten().copied().collect::<Vec<f32>>())
            })
        });
        std::fs::write(dir.join(file), original).unwrap();
    }
    fuzz.finish();
    let _ = std::fs::remove_dir_all(&root);
}

/// Stored tokens as `velox encode` writes them, mutated: the scene file (its bytes, its
/// header's length and JSON, NaN and Inf in its tensors) through `read_scene_file` and
/// `TokenFolder::read`, and the manifest (its JSON leaves and bytes) through
/// `TokenManifest::read`.
#[test]
fn fuzz_token_files_and_manifests() {
    let dir = temp_dir("tokens");
    let origin = TokenOrigin {
        checkpoint: dir.join("ae.safetensors"),
        checkpoint_hash: "0123456789abcdef".into(),
        config: AutoencoderConfig::tiny(),
        seed: 3,
        precision: velox::engine::Precision::F32,
        source: Default::default(),
    };
    let (k, d) = origin.shape();
    let mut rng = Rng::new(0x70c);
    let values: Vec<f32> = (0..k * d).map(|_| rng.range(-2.0, 2.0) as f32).collect();
    let points: Vec<f32> =
        (0..k).flat_map(|i| [rng.range(-1.0, 1.0) as f32, 0.5, -0.5, (i % 24) as f32 / 100.0]).collect();
    let stored = SceneTokens::new("scene_00000", values, points, d).unwrap();
    let path = write_scene_file(&dir, &origin, &stored).unwrap();
    let scenes = vec!["scene_00000".to_string(), "scene_00001".to_string()];
    let manifest = TokenManifest::new(origin.clone(), scenes, &TokenStats::of(&stored.tokens, d));
    manifest.write(&dir).unwrap();
    // The recorded checkpoint does not exist: the folder reads unchecked, as it would.
    let folder = TokenFolder {
        dir: dir.clone(),
        manifest: manifest.clone(),
        checkpoint: CheckpointCheck::Unchecked("no checkpoint".into()),
    };
    let valid_tokens = |(o, t): (TokenOrigin, SceneTokens)| -> Result<(), String> {
        o.config.validate().map_err(|e| format!("accepted an invalid config: {e}"))?;
        let (k, d) = o.shape();
        if t.token_dim != d || t.tokens.len() != k * d || t.query_points.len() != k * 4 {
            return Err(format!(
                "accepted tokens of {} values and {} query values",
                t.tokens.len(),
                t.query_points.len()
            ));
        }
        all_finite("tokens", &t.tokens)?;
        all_finite("query points", &t.query_points)
    };

    let good = std::fs::read(&path).unwrap();
    // NaN and Inf at each end and at a random place of every tensor's data.
    let cases = safetensors_mutations(&mut rng, &good, &[], true);
    let mut fuzz =
        Fuzz::new("stored tokens (velox_models::velox::tokens::read_scene_file, TokenFolder::read)");
    for (what, bytes) in cases {
        std::fs::write(&path, &bytes).unwrap();
        fuzz.case(&what, || {
            named_or_valid(read_scene_file(&path), &path, valid_tokens)?;
            named_or_valid(folder.read("scene_00000").map(|t| (origin.clone(), t)), &path, valid_tokens)
        });
    }
    fuzz.finish();

    let manifest_path = dir.join(MANIFEST);
    let good = std::fs::read_to_string(&manifest_path).unwrap();
    let mut cases: Vec<(String, Vec<u8>)> =
        json_mutations(&mut rng, &good, 400).into_iter().map(|(w, t)| (w, t.into_bytes())).collect();
    cases.extend(byte_mutations(&mut rng, good.as_bytes(), 150));
    let mut fuzz = Fuzz::new("token manifest (velox_models::velox::tokens::TokenManifest::read)");
    for (what, bytes) in cases {
        std::fs::write(&manifest_path, &bytes).unwrap();
        fuzz.case(&what, || {
            named_or_valid(TokenManifest::read(&dir), &manifest_path, |m| {
                m.origin.config.validate().map_err(|e| format!("accepted an invalid config: {e}"))?;
                finite_json(&serde_json::to_value(&m).unwrap(), "")?;
                let d = m.origin.shape().1;
                if m.scenes.is_empty()
                    || m.mean.len() != d
                    || m.std.len() != d
                    || m.std.iter().any(|s| *s < 0.0)
                {
                    return Err(format!("accepted an inconsistent manifest: {m:?}"));
                }
                Ok(())
            })
        });
    }
    fuzz.finish();
    let _ = std::fs::remove_dir_all(&dir);
}
