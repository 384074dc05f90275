//! DINOv2 (Oquab et al. 2023), the frozen image network of the generator's condition tokens:
//! a ViT with patch size 14, a class token, learned positions on a square grid (37 x 37 for the
//! published models) interpolated bicubically to the input's patch grid, pre-norm blocks of
//! self-attention and a GELU feed-forward, each scaled by LayerScale before its residual add,
//! and a final LayerNorm. Inference only; weights come from a safetensors file in the Hugging
//! Face layout (`facebook/dinov2-large`, or the names `transformers` 5 writes).
//!
//! What the engine runs, per image of `N = gh x gw` patches and `1 + N` tokens:
//! - the patches (`3 x 14 x 14` each, channel-major, as the convolution's weight is laid out)
//!   are rows of a matrix with one zero row in front for the class token; one product with the
//!   patch weight gives every row (the zero row stays exactly zero), and one broadcast add of a
//!   table per grid size puts in the patch bias plus the interpolated positions, and the class
//!   token plus its position in row 0. The table is computed on the host in f64.
//! - LayerScale is folded into the weights it follows: `gamma * (x W + b) = x (W diag gamma) +
//!   gamma b`, which saves a dispatch per residual branch (the fixture test bounds what the
//!   different rounding costs).
//! - the images of a pass are attention segments of their own; passes hold whole images and are
//!   sized so that the widest activation fits one storage binding of the device, and every
//!   block is its own submission, so memory stays at one block's activations.
//!
//! In an f16 recording the products and the attention read f16 operands ([`Linear::forward`]);
//! norms, softmax statistics and the residual stream stay f32.
//!
//! Tests: `tests/models/dinov2.rs` (against the `transformers` package's outputs on fixtures,
//! weight names, the position resampling, the parameter count).

use std::collections::BTreeMap;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors};
use velox_engine::ops::attention::Segments;
use velox_engine::ops::binary::{binary, Binary};
use velox_engine::{DType, Error, Gpu, Precision, Recorder, Result, Tensor};

use crate::layers::attention::MultiHeadAttention;
use crate::layers::feedforward::GeluMlp;
use crate::layers::linear::Linear;
use crate::layers::norm::LayerNorm;
use crate::layers::Param;

/// Patch side in pixels.
pub const PATCH: usize = 14;
/// Values per patch row: 3 channels of `PATCH x PATCH`.
pub const PATCH_VALUES: usize = 3 * PATCH * PATCH;
/// The ImageNet statistics DINOv2 was trained with: pixels in [0, 1] are normalised as
/// `(p - mean) / std` per channel before the network reads them.
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];
/// Head width of every published DINOv2 (small 6, base 12, large 16, giant 24 heads of 64); used
/// when no `config.json` beside the weights says otherwise.
pub const HEAD_WIDTH: usize = 64;

/// The architecture, read from the weights' shapes (and `config.json` beside them, if any).
#[derive(Clone, Debug, PartialEq)]
pub struct Dinov2Config {
    pub width: usize,
    pub depth: usize,
    pub heads: usize,
    /// Feed-forward hidden width.
    pub hidden: usize,
    /// Side of the square grid the positions were trained on.
    pub grid: usize,
    pub eps: f32,
}

impl Dinov2Config {
    /// `facebook/dinov2-large` (ViT-L/14): 304 M parameters.
    pub fn large() -> Dinov2Config {
        Dinov2Config { width: 1024, depth: 24, heads: 16, hidden: 4096, grid: 37, eps: 1e-6 }
    }

    pub fn num_parameters(&self) -> usize {
        let (d, h) = (self.width, self.hidden);
        let block = 4 * (d * d + d) + (d * h + h) + (h * d + d) + 4 * d + 2 * d;
        // patch weight and bias, class and mask tokens, positions, blocks, final norm.
        PATCH_VALUES * d + d + 2 * d + (1 + self.grid * self.grid) * d + self.depth * block + 2 * d
    }
}

struct Block {
    norm1: LayerNorm,
    attention: MultiHeadAttention,
    norm2: LayerNorm,
    mlp: GeluMlp,
}

pub struct Dinov2 {
    pub config: Dinov2Config,
    /// `[PATCH_VALUES, width]`, no bias (the bias is in the position table).
    patch: Linear,
    patch_bias: Vec<f32>,
    cls: Vec<f32>,
    /// `[1 + grid^2, width]`: the class token's position, then the grid's in raster order.
    positions: Vec<f32>,
    blocks: Vec<Block>,
    norm: LayerNorm,
    /// The weight file's hash (as `velox_models::velox::tokens::checkpoint_hash` gives it), by
    /// which a generator names the DINOv2 it read; none for random weights.
    pub file_hash: Option<String>,
}

/// A weight file's tensors by name, as f32 with their shapes.
type Tensors = BTreeMap<String, (Vec<usize>, Vec<f32>)>;

fn invalid(path: &Path, what: String) -> Error {
    Error::Invalid(format!("DINOv2 weights {}: {what}", path.display()))
}

/// Every tensor of a safetensors file as f32 (from f32, f16 or bf16), and the file's hash.
fn read_safetensors(path: &Path) -> Result<(Tensors, String)> {
    let bytes = std::fs::read(path).map_err(|e| invalid(path, format!("cannot read: {e}")))?;
    let mut hash = crate::velox::tokens::Fnv1a::new();
    hash.update(&bytes);
    let hash = crate::velox::tokens::hash_hex(hash.finish());
    let file = SafeTensors::deserialize(&bytes)
        .map_err(|e| invalid(path, format!("not a safetensors file, or truncated: {e}")))?;
    let mut out = Tensors::new();
    for (name, t) in file.tensors() {
        let data = t.data();
        let values: Vec<f32> = match t.dtype() {
            Dtype::F32 => {
                data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
            }
            Dtype::F16 => {
                data.chunks_exact(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect()
            }
            Dtype::BF16 => {
                data.chunks_exact(2).map(|b| half::bf16::from_le_bytes([b[0], b[1]]).to_f32()).collect()
            }
            other => {
                return Err(invalid(path, format!("tensor {name:?} is {other:?}; expected F32, F16 or BF16")))
            }
        };
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(invalid(path, format!("tensor {name:?} holds a non-finite value at {i}")));
        }
        out.insert(name, (t.shape().to_vec(), values));
    }
    Ok((out, hash))
}

/// `num_attention_heads` and `layer_norm_eps` from a Hugging Face `config.json` beside the
/// weights, where there is one.
fn read_hf_config(path: &Path) -> Result<(Option<usize>, Option<f32>)> {
    let Some(config) = path.parent().map(|d| d.join("config.json")).filter(|p| p.is_file()) else {
        return Ok((None, None));
    };
    let text = std::fs::read_to_string(&config).map_err(|e| invalid(&config, format!("cannot read: {e}")))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| invalid(&config, format!("not JSON: {e}")))?;
    let heads = json.get("num_attention_heads").and_then(|v| v.as_u64()).map(|v| v as usize);
    let eps = json.get("layer_norm_eps").and_then(|v| v.as_f64()).map(|v| v as f32);
    Ok((heads, eps))
}

/// Reads tensors by either of the two naming schemes of the Hugging Face DINOv2.
struct Reader<'a> {
    path: &'a Path,
    tensors: Tensors,
}

impl Reader<'_> {
    fn take(&mut self, names: &[&str], shape: &[usize]) -> Result<Vec<f32>> {
        let Some((name, (s, v))) = names.iter().find_map(|n| self.tensors.remove_entry(*n)) else {
            return Err(invalid(
                self.path,
                format!("tensor {:?} is missing (is this a DINOv2 file?)", names[0]),
            ));
        };
        if s != shape {
            return Err(invalid(self.path, format!("tensor {name:?} has shape {s:?}, expected {shape:?}")));
        }
        Ok(v)
    }

    fn shape_of(&self, name: &str) -> Result<Vec<usize>> {
        self.tensors
            .get(name)
            .map(|(s, _)| s.clone())
            .ok_or_else(|| invalid(self.path, format!("tensor {name:?} is missing (is this a DINOv2 file?)")))
    }
}

/// `[out, in]` (PyTorch's Linear) to `[in, out]`, each output column scaled by `scale[o]`.
fn transpose_scaled(w: &[f32], out: usize, inp: usize, scale: Option<&[f32]>) -> Vec<f32> {
    let mut t = vec![0.0f32; w.len()];
    for o in 0..out {
        let s = scale.map_or(1.0, |s| s[o] as f64);
        for i in 0..inp {
            t[i * out + o] = (w[o * inp + i] as f64 * s) as f32;
        }
    }
    t
}

impl Dinov2 {
    /// Loads a safetensors file of DINOv2 weights; the head count comes from `config.json` beside
    /// it where there is one, else every head is [`HEAD_WIDTH`] wide.
    pub fn load(gpu: &Gpu, path: &Path) -> Result<Dinov2> {
        let (tensors, hash) = read_safetensors(path)?;
        let (heads, eps) = read_hf_config(path)?;
        let d = Dinov2::from_tensors(gpu, path, tensors, heads, eps.unwrap_or(1e-6))?;
        Ok(Dinov2 { file_hash: Some(hash), ..d })
    }

    fn from_tensors(
        gpu: &Gpu,
        path: &Path,
        tensors: Tensors,
        heads: Option<usize>,
        eps: f32,
    ) -> Result<Dinov2> {
        let mut r = Reader { path, tensors };
        if r.tensors.keys().any(|k| k.contains("register_tokens")) {
            return Err(invalid(path, "DINOv2 with registers is not supported; give the plain model".into()));
        }
        if r.tensors.keys().any(|k| k.contains("weights_in")) {
            return Err(invalid(path, "the SwiGLU feed-forward (DINOv2 giant) is not supported".into()));
        }
        // Some exports prefix every name with the model's base name.
        if r.tensors.keys().all(|k| k.starts_with("dinov2.")) {
            r.tensors = std::mem::take(&mut r.tensors)
                .into_iter()
                .map(|(k, v)| (k["dinov2.".len()..].to_string(), v))
                .collect();
        }
        let cls_shape = r.shape_of("embeddings.cls_token")?;
        let width = *cls_shape.last().unwrap_or(&0);
        let pos_shape = r.shape_of("embeddings.position_embeddings")?;
        let n_pos = if pos_shape.len() == 3 { pos_shape[1] } else { 0 };
        let grid = ((n_pos.saturating_sub(1)) as f64).sqrt().round() as usize;
        if width == 0 || grid == 0 || grid * grid + 1 != n_pos {
            return Err(invalid(
                path,
                format!("positions {pos_shape:?} are not 1 + a square grid of width {width}"),
            ));
        }
        let depth = (0..)
            .take_while(|i| r.tensors.keys().any(|k| k.starts_with(&format!("encoder.layer.{i}."))))
            .count();
        let hidden = r.shape_of("encoder.layer.0.mlp.fc1.weight")?[0];
        let heads = heads.unwrap_or(width / HEAD_WIDTH);
        if heads == 0 || !width.is_multiple_of(heads) {
            return Err(invalid(path, format!("width {width} does not split into {heads} heads")));
        }
        let config = Dinov2Config { width, depth, heads, hidden, grid, eps };
        let cls = r.take(&["embeddings.cls_token"], &[1, 1, width])?;
        let positions = r.take(&["embeddings.position_embeddings"], &[1, n_pos, width])?;
        let conv = r.take(&["embeddings.patch_embeddings.projection.weight"], &[width, 3, PATCH, PATCH])?;
        let patch_bias = r.take(&["embeddings.patch_embeddings.projection.bias"], &[width])?;
        let frozen = |shape: &[usize], v: &[f32]| Param::frozen(gpu, shape, v);
        let patch = Linear::new(
            frozen(&[PATCH_VALUES, width], &transpose_scaled(&conv, width, PATCH_VALUES, None))?,
            None,
        )?;
        let norm = |r: &mut Reader, name: &str| -> Result<LayerNorm> {
            let w = r.take(&[&format!("{name}.weight")], &[width])?;
            let b = r.take(&[&format!("{name}.bias")], &[width])?;
            LayerNorm::new(width, Some((frozen(&[width], &w)?, frozen(&[width], &b)?)), eps)
        };
        // A linear layer from PyTorch's `[out, in]` weight, named either way, optionally scaled.
        let linear = |r: &mut Reader, names: &[String], inp: usize, out: usize, scale: Option<&[f32]>| {
            let ws: Vec<String> = names.iter().map(|n| format!("{n}.weight")).collect();
            let bs: Vec<String> = names.iter().map(|n| format!("{n}.bias")).collect();
            let w = r.take(&ws.iter().map(String::as_str).collect::<Vec<_>>(), &[out, inp])?;
            let mut b = r.take(&bs.iter().map(String::as_str).collect::<Vec<_>>(), &[out])?;
            if let Some(s) = scale {
                b.iter_mut().zip(s).for_each(|(b, s)| *b = (*b as f64 * *s as f64) as f32);
            }
            Linear::new(
                frozen(&[inp, out], &transpose_scaled(&w, out, inp, scale))?,
                Some(frozen(&[out], &b)?),
            )
        };
        let mut blocks = Vec::with_capacity(depth);
        for i in 0..depth {
            let p = format!("encoder.layer.{i}");
            let ls1 = r.take(&[&format!("{p}.layer_scale1.lambda1")], &[width])?;
            let ls2 = r.take(&[&format!("{p}.layer_scale2.lambda1")], &[width])?;
            let names =
                |hub: &str, v5: &str| vec![format!("{p}.attention.{hub}"), format!("{p}.attention.{v5}")];
            let q = linear(&mut r, &names("attention.query", "q_proj"), width, width, None)?;
            let k = linear(&mut r, &names("attention.key", "k_proj"), width, width, None)?;
            let v = linear(&mut r, &names("attention.value", "v_proj"), width, width, None)?;
            let o = linear(&mut r, &names("output.dense", "o_proj"), width, width, Some(&ls1))?;
            let fc1 = linear(&mut r, &[format!("{p}.mlp.fc1")], width, hidden, None)?;
            let fc2 = linear(&mut r, &[format!("{p}.mlp.fc2")], hidden, width, Some(&ls2))?;
            blocks.push(Block {
                norm1: norm(&mut r, &format!("{p}.norm1"))?,
                attention: MultiHeadAttention::new(q, k, v, o, heads)?,
                norm2: norm(&mut r, &format!("{p}.norm2"))?,
                mlp: GeluMlp { fc1, fc2 },
            });
        }
        let final_norm = norm(&mut r, "layernorm")?;
        // Only used for masked pre-training.
        r.tensors.remove("embeddings.mask_token");
        if let Some(extra) = r.tensors.keys().next() {
            return Err(invalid(
                path,
                format!("unexpected tensor {extra:?} ({} left unread)", r.tensors.len()),
            ));
        }
        Ok(Dinov2 { config, patch, patch_bias, cls, positions, blocks, norm: final_norm, file_hash: None })
    }

    /// A DINOv2 of `config` with random weights (for benchmarks): every matrix and position
    /// N(0, 0.02^2), norms at 1 and 0, LayerScale 0.1, as an untrained ViT starts.
    pub fn random(gpu: &Gpu, config: &Dinov2Config, seed: u64) -> Result<Dinov2> {
        let mut rng = velox_engine::rng::Rng::new(seed);
        let (d, h) = (config.width, config.hidden);
        let mut t = Tensors::new();
        let mut add = |name: String, shape: Vec<usize>, fill: Option<f32>| {
            let n = shape.iter().product();
            let v = match fill {
                Some(c) => vec![c; n],
                None => rng.normal_vec(n).iter().map(|x| 0.02 * x).collect(),
            };
            t.insert(name, (shape, v));
        };
        add("embeddings.cls_token".into(), vec![1, 1, d], None);
        add("embeddings.position_embeddings".into(), vec![1, 1 + config.grid * config.grid, d], None);
        add("embeddings.patch_embeddings.projection.weight".into(), vec![d, 3, PATCH, PATCH], None);
        add("embeddings.patch_embeddings.projection.bias".into(), vec![d], Some(0.0));
        for i in 0..config.depth {
            let p = format!("encoder.layer.{i}");
            for (name, out, inp) in [
                ("attention.q_proj", d, d),
                ("attention.k_proj", d, d),
                ("attention.v_proj", d, d),
                ("attention.o_proj", d, d),
                ("mlp.fc1", h, d),
                ("mlp.fc2", d, h),
            ] {
                add(format!("{p}.{name}.weight"), vec![out, inp], None);
                add(format!("{p}.{name}.bias"), vec![out], Some(0.0));
            }
            for n in ["norm1", "norm2"] {
                add(format!("{p}.{n}.weight"), vec![d], Some(1.0));
                add(format!("{p}.{n}.bias"), vec![d], Some(0.0));
            }
            for n in ["layer_scale1", "layer_scale2"] {
                add(format!("{p}.{n}.lambda1"), vec![d], Some(0.1));
            }
        }
        add("layernorm.weight".into(), vec![d], Some(1.0));
        add("layernorm.bias".into(), vec![d], Some(0.0));
        Dinov2::from_tensors(gpu, Path::new("(random weights)"), t, Some(config.heads), config.eps)
    }

    /// The patch grid of an image of `height x width` pixels, which must both be positive
    /// multiples of [`PATCH`].
    pub fn grid_of(height: usize, width: usize) -> Result<(usize, usize)> {
        if height == 0 || width == 0 || !height.is_multiple_of(PATCH) || !width.is_multiple_of(PATCH) {
            return Err(Error::Invalid(format!(
                "DINOv2 reads images whose sides are positive multiples of {PATCH} pixels, got {width} x {height}"
            )));
        }
        Ok((height / PATCH, width / PATCH))
    }

    /// `[1 + gh * gw, width]`: row 0 the class token plus its position, row `1 + i` the patch
    /// bias plus the position of patch `i` (raster order), the trained grid resampled bicubically
    /// to `gh x gw` as PyTorch's `interpolate(mode="bicubic", align_corners=False)` does (the
    /// trained grid itself when it already fits and is square, as the reference code does).
    pub fn position_table(&self, gh: usize, gw: usize) -> Vec<f32> {
        let (d, g) = (self.config.width, self.config.grid);
        let pos = |i: usize, j: usize, c: usize| self.positions[(1 + i * g + j) * d + c] as f64;
        let ys = cubic_taps(g, gh);
        let xs = cubic_taps(g, gw);
        let mut table = vec![0.0f32; (1 + gh * gw) * d];
        for (t, (c, p)) in table.iter_mut().zip(self.cls.iter().zip(&self.positions)) {
            *t = (*c as f64 + *p as f64) as f32;
        }
        for (oy, (iy, wy)) in ys.iter().enumerate() {
            for (ox, (ix, wx)) in xs.iter().enumerate() {
                let row = &mut table[(1 + oy * gw + ox) * d..][..d];
                for (c, out) in row.iter_mut().enumerate() {
                    let mut v = 0.0f64;
                    for (a, &y) in iy.iter().enumerate() {
                        let mut across = 0.0f64;
                        for (b, &x) in ix.iter().enumerate() {
                            across += wx[b] * pos(y, x, c);
                        }
                        v += wy[a] * across;
                    }
                    *out = (self.patch_bias[c] as f64 + v) as f32;
                }
            }
        }
        table
    }

    /// The patches of `frames` images as rows, `[frames * N, PATCH_VALUES]`: per image its
    /// patches in raster order, each channel-major (as the patch convolution's weight is laid
    /// out). `pixels` are `[frames, 3, height, width]`; non-finite values are refused.
    pub fn image_patches(pixels: &[f32], frames: usize, height: usize, width: usize) -> Result<Vec<f32>> {
        let (gh, gw) = Dinov2::grid_of(height, width)?;
        if pixels.len() != frames * 3 * height * width {
            return Err(Error::Shape(format!(
                "DINOv2: {} pixel values for {frames} images of 3 x {height} x {width}",
                pixels.len()
            )));
        }
        if let Some(i) = pixels.iter().position(|v| !v.is_finite()) {
            return Err(Error::Invalid(format!("DINOv2: pixel value {i} is not finite")));
        }
        let mut rows = vec![0.0f32; frames * gh * gw * PATCH_VALUES];
        for f in 0..frames {
            let image = &pixels[f * 3 * height * width..][..3 * height * width];
            for py in 0..gh {
                for px in 0..gw {
                    let row = &mut rows[((f * gh + py) * gw + px) * PATCH_VALUES..][..PATCH_VALUES];
                    for c in 0..3 {
                        for ky in 0..PATCH {
                            let src = &image[(c * height + py * PATCH + ky) * width + px * PATCH..][..PATCH];
                            row[(c * PATCH + ky) * PATCH..][..PATCH].copy_from_slice(src);
                        }
                    }
                }
            }
        }
        Ok(rows)
    }

    /// Rows for the patch product, `[frames * (1 + N), PATCH_VALUES]`: per image a zero row
    /// (the class token's place) and then its [`Dinov2::image_patches`].
    pub fn patch_rows(pixels: &[f32], frames: usize, height: usize, width: usize) -> Result<Vec<f32>> {
        let patches = Dinov2::image_patches(pixels, frames, height, width)?;
        let per_image = patches.len() / frames.max(1);
        let mut rows = Vec::with_capacity(patches.len() + frames * PATCH_VALUES);
        for image in patches.chunks(per_image.max(1)) {
            rows.extend_from_slice(&[0.0; PATCH_VALUES]);
            rows.extend_from_slice(image);
        }
        Ok(rows)
    }

    /// The embedded tokens `[frames * (1 + N), width]` from patch rows (see [`Dinov2::patch_rows`])
    /// and a position table (see [`Dinov2::position_table`]) on the device.
    pub fn record_embed(&self, rec: &mut Recorder, rows: &Tensor, table: &Tensor) -> Result<Tensor> {
        let d = self.config.width;
        let per_image = table.numel() / d;
        let n = rows.shape()[0];
        if table.shape() != [per_image, d] || per_image == 0 || !n.is_multiple_of(per_image) {
            return Err(Error::Shape(format!(
                "DINOv2: rows {rows:?} do not fit the position table {table:?}"
            )));
        }
        let (x, _) = self.patch.forward(rec, rows)?;
        let x = binary(rec, &x.reshape(&[n / per_image, per_image, d])?, table, Binary::Add)?;
        x.reshape(&[n, d])
    }

    /// One block over `x [rows, width]`, images as attention segments.
    pub fn record_block(&self, rec: &mut Recorder, i: usize, x: &Tensor, seg: &Segments) -> Result<Tensor> {
        let b = &self.blocks[i];
        let (h, _) = b.norm1.forward(rec, x)?;
        let (a, _) = b.attention.forward(rec, &h, None, seg)?;
        let x = binary(rec, x, &a, Binary::Add)?;
        let (h, _) = b.norm2.forward(rec, &x)?;
        let (m, _) = b.mlp.forward(rec, &h)?;
        binary(rec, &x, &m, Binary::Add)
    }

    /// The final LayerNorm.
    pub fn record_norm(&self, rec: &mut Recorder, x: &Tensor) -> Result<Tensor> {
        Ok(self.norm.forward(rec, x)?.0)
    }

    /// How many images of `tokens` tokens run in one pass: as many as keep the widest activation
    /// (the feed-forward's hidden layer) inside one storage binding and under 1 GiB.
    pub fn images_per_pass(&self, gpu: &Gpu, tokens: usize) -> usize {
        let limit = gpu.caps().max_storage_buffer_range.min(1 << 30);
        let per_image = (tokens * self.config.hidden.max(PATCH_VALUES) * 4) as u64;
        (limit / per_image.max(1)).max(1) as usize
    }

    /// `last_hidden_state` of `frames` images (`[frames, 3, height, width]`, normalised), as
    /// `[frames * (1 + N), width]` on the device: per image the class token then its patches.
    /// Runs [`Dinov2::images_per_pass`] images a pass, one submission per block, in `precision`.
    pub fn forward(
        &self,
        gpu: &Gpu,
        pixels: &[f32],
        frames: usize,
        height: usize,
        width: usize,
        precision: Precision,
    ) -> Result<Tensor> {
        let (gh, gw) = Dinov2::grid_of(height, width)?;
        let rows = Dinov2::patch_rows(pixels, frames, height, width)?;
        let (d, per_image) = (self.config.width, 1 + gh * gw);
        let table = Tensor::from_slice(gpu, &[per_image, d], &self.position_table(gh, gw))?;
        let out = Tensor::empty(gpu, &[frames * per_image, d], DType::F32)?;
        let chunk = self.images_per_pass(gpu, per_image);
        let mut f0 = 0;
        while f0 < frames {
            let n = chunk.min(frames - f0);
            let part = Tensor::from_slice(
                gpu,
                &[n * per_image, PATCH_VALUES],
                &rows[f0 * per_image * PATCH_VALUES..(f0 + n) * per_image * PATCH_VALUES],
            )?;
            let seg = Segments::from_lengths(gpu, &vec![per_image; n], &vec![per_image; n])?;
            let mut rec = gpu.recorder()?;
            rec.set_precision(precision);
            let mut x = self.record_embed(&mut rec, &part, &table)?;
            for i in 0..self.blocks.len() {
                x = self.record_block(&mut rec, i, &x, &seg)?;
                rec.submit()?;
                rec = gpu.recorder()?;
                rec.set_precision(precision);
            }
            let y = self.record_norm(&mut rec, &x)?;
            rec.copy_rows(&y, 0, &out, f0 * per_image, n * per_image)?;
            rec.submit()?;
            f0 += n;
        }
        Ok(out)
    }
}

impl Dinov2 {
    /// The patch features of `frames` images (the last layer's, after the final norm, without
    /// the class tokens): `[frames * N, width]` on the device, as the generator's condition
    /// reads them.
    pub fn patch_features(
        &self,
        gpu: &Gpu,
        pixels: &[f32],
        frames: usize,
        height: usize,
        width: usize,
        precision: Precision,
    ) -> Result<Tensor> {
        let (gh, gw) = Dinov2::grid_of(height, width)?;
        let n = gh * gw;
        let all = self.forward(gpu, pixels, frames, height, width, precision)?;
        let out = Tensor::empty(gpu, &[frames * n, self.config.width], DType::F32)?;
        let mut rec = gpu.recorder()?;
        for f in 0..frames {
            rec.copy_rows(&all, f * (1 + n) + 1, &out, f * n, n)?;
        }
        rec.submit()?;
        Ok(out)
    }
}

/// For each of `n_out` outputs resampled from `n_in` inputs: the four input indices (clamped to
/// the border) and their cubic convolution weights (`A = -0.75`), with PyTorch's source
/// coordinate `(o + 0.5) n_in / n_out - 0.5` and no clamping of it (its bicubic mode).
fn cubic_taps(n_in: usize, n_out: usize) -> Vec<([usize; 4], [f64; 4])> {
    const A: f64 = -0.75;
    let near = |x: f64| ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
    let far = |x: f64| ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;
    let scale = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|o| {
            let real = (o as f64 + 0.5) * scale - 0.5;
            let i = real.floor();
            let t = real - i;
            let idx =
                std::array::from_fn(|k| (i as isize - 1 + k as isize).clamp(0, n_in as isize - 1) as usize);
            (idx, [far(t + 1.0), near(t), near(1.0 - t), far(2.0 - t)])
        })
        .collect()
}
