//! The Velox Gaussian decoder G (paper section 3.3; MODELS.md, Gaussian decoder): the dynamic
//! tokens and a frame time to 3D Gaussians.
//!
//! - Queries: the occupied voxels of a `grid`^3 grid over [-1, 1]^3 at frame tau (from the
//!   frame's points in training, [`occupied_voxels`]); each query's feature is its centre, tau
//!   and their Fourier embeddings, through a linear layer.
//! - `blocks` Perceiver blocks, pre-norm RMSNorm, SwiGLU feed-forwards: global cross-attention
//!   from the queries to every token, then `self_layers` self-attention layers within voxel
//!   windows of `window_voxels`^3 voxels (every second one shifted by half a window).
//! - Head: RMSNorm and a linear layer to G x 14 numbers per voxel, activated by
//!   [`velox_engine::ops::gaussian_head`] into the rasteriser's parameters.
//!
//! The backward pass returns the gradient with respect to the tokens, which the encoder needs.

use velox_engine::ops::attention::Segments;
use velox_engine::ops::binary::{binary, binary_into, Binary};
use velox_engine::ops::columns::copy_columns;
use velox_engine::ops::fill::fill;
use velox_engine::ops::gaussian_head::{head_backward, head_forward, HeadRange, RAW};
use velox_engine::ops::raster::Gaussians;
use velox_engine::ops::window::WindowGrid;
use velox_engine::{DType, Error, Gpu, Recorder, Result, Tensor};

use crate::config::GaussianConfig;
use crate::layers::attention::{MultiHeadAttention, MultiHeadAttentionCache};
use crate::layers::feedforward::{GeluMlp, GeluMlpCache};
use crate::layers::linear::LinearCache;
use crate::layers::norm::RmsNormCache;
use crate::layers::{Fourier, Linear, Param, RmsNorm};
use crate::params::{Init, ParamBuilder, ParamStore};
use crate::velox::blocks::{
    ff, ff_params, linear, linear_params, norm, window_layer_params, FeedForward, FeedForwardCache,
    WindowLayer, WindowLayerCache, WindowLayout,
};
use crate::velox::cloud::CHANNELS;

struct Block {
    norm_q: RmsNorm,
    cross: MultiHeadAttention,
    cross_ff: FeedForward,
    layers: Vec<WindowLayer>,
}

pub struct GaussianDecoder {
    pub cfg: GaussianConfig,
    fourier_xyz: Fourier,
    fourier_tau: Fourier,
    input: Dense,
    blocks: Vec<Block>,
    head_norm: RmsNorm,
    head: Dense,
}

struct BlockCache {
    norm_q: RmsNormCache,
    cross: MultiHeadAttentionCache,
    cross_ff: FeedForwardCache,
    layers: Vec<WindowLayerCache>,
}

/// The frame groups of a batch of voxels and the tokens each attends to: the voxels are
/// `groups` in order, `(tau, count)` each, and `segments` gives each segment of voxels (a
/// sample's frames) its rows of the tokens.
#[derive(Clone, Debug)]
pub struct VoxelFrames {
    pub groups: Vec<(f32, usize)>,
    pub segments: Segments,
}

pub struct GaussianCache {
    centres: Tensor,
    windows: [WindowLayout; 2],
    cross_segments: Segments,
    input: DenseCache,
    blocks: Vec<BlockCache>,
    head_norm: RmsNormCache,
    head: DenseCache,
    raw: Tensor,
    tokens_shape: Vec<usize>,
}

/// Centres (x, y, z) of the voxels of a `grid`^3 grid over [-1, 1]^3 holding at least one
/// point of frame `tau` (rows of the 7-channel cloud whose tau is within 1e-4), in voxel order.
pub fn occupied_voxels(cloud: &[f32], tau: f32, grid: usize) -> Vec<f32> {
    let cell = 2.0 / grid as f32;
    let mut ids: Vec<usize> = cloud
        .chunks(CHANNELS)
        .filter(|p| (p[6] - tau).abs() < 1e-4)
        .map(|p| {
            let c = |v: f32| (((v + 1.0) / cell).floor().max(0.0) as usize).min(grid - 1);
            (c(p[0]) * grid + c(p[1])) * grid + c(p[2])
        })
        .collect();
    ids.sort_unstable();
    ids.dedup();
    let centre = |i: usize| -1.0 + (i as f32 + 0.5) * cell;
    ids.iter()
        .flat_map(|&id| [centre(id / (grid * grid)), centre(id / grid % grid), centre(id % grid)])
        .collect()
}

/// A linear layer, or a GELU MLP through a hidden width (`fc1`, `fc2` under its name). A
/// decoder holds two, so the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
enum Dense {
    Linear(Linear),
    Mlp(GeluMlp),
}

enum DenseCache {
    Linear(LinearCache),
    Mlp(GeluMlpCache),
}

impl Dense {
    fn new(store: &ParamStore, name: &str, hidden: usize) -> Result<Dense> {
        Ok(match hidden {
            0 => Dense::Linear(linear(store, name, true)?),
            _ => {
                let p = |l: &str, x: &str| Param::from_store(store, &format!("{name}.{l}.{x}"));
                Dense::Mlp(GeluMlp::new(p("fc1", "w")?, p("fc1", "b")?, p("fc2", "w")?, p("fc2", "b")?)?)
            }
        })
    }

    fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, DenseCache)> {
        Ok(match self {
            Dense::Linear(l) => {
                let (y, c) = l.forward(rec, x)?;
                (y, DenseCache::Linear(c))
            }
            Dense::Mlp(m) => {
                let (y, c) = m.forward(rec, x)?;
                (y, DenseCache::Mlp(c))
            }
        })
    }

    fn backward(&self, rec: &mut Recorder, cache: &DenseCache, dy: &Tensor) -> Result<Tensor> {
        match (self, cache) {
            (Dense::Linear(l), DenseCache::Linear(c)) => l.backward(rec, c, dy),
            (Dense::Mlp(m), DenseCache::Mlp(c)) => m.backward(rec, c, dy),
            _ => Err(Error::Invalid("gaussian decoder: a cache of another layer".into())),
        }
    }

    fn param_grads(&self, rec: &mut Recorder, cache: &DenseCache, dy: &Tensor) -> Result<()> {
        match (self, cache) {
            (Dense::Linear(l), DenseCache::Linear(c)) => l.param_grads(rec, c, dy),
            (Dense::Mlp(m), DenseCache::Mlp(c)) => m.param_grads(rec, c, dy),
            _ => Err(Error::Invalid("gaussian decoder: a cache of another layer".into())),
        }
    }
}

fn attention_params(b: &mut ParamBuilder, name: &str, width: usize, context: usize) -> Result<()> {
    linear_params(b, &format!("{name}.q"), width, width, false)?;
    linear_params(b, &format!("{name}.k"), context, width, false)?;
    linear_params(b, &format!("{name}.v"), context, width, false)?;
    linear_params(b, &format!("{name}.o"), width, width, false)
}

impl GaussianDecoder {
    /// Width of a query's feature: centre and its Fourier embedding, tau and its.
    pub fn feature_width(cfg: &GaussianConfig) -> usize {
        (3 + 6 * cfg.xyz_freqs) + (1 + 2 * cfg.tau_freqs)
    }

    pub fn register(
        b: &mut ParamBuilder,
        prefix: &str,
        cfg: &GaussianConfig,
        token_dim: usize,
    ) -> Result<()> {
        let w = cfg.width;
        let input = format!("{prefix}.input");
        match cfg.input_hidden {
            0 => linear_params(b, &input, Self::feature_width(cfg), w, true)?,
            h => {
                linear_params(b, &format!("{input}.fc1"), Self::feature_width(cfg), h, true)?;
                linear_params(b, &format!("{input}.fc2"), h, w, true)?;
            }
        }
        for i in 0..cfg.blocks {
            let blk = format!("{prefix}.block{i}");
            b.add(&format!("{blk}.norm_q"), &[w], Init::Ones)?;
            attention_params(b, &format!("{blk}.cross"), w, token_dim)?;
            ff_params(b, &format!("{blk}.cross_ff"), w, cfg.ffn_ratio)?;
            for l in 0..cfg.self_layers {
                window_layer_params(b, &format!("{blk}.self{l}"), w, cfg.ffn_ratio)?;
            }
        }
        b.add(&format!("{prefix}.head_norm"), &[w], Init::Ones)?;
        // A small last layer: the first renders start from faint, mid-sized Gaussians at the
        // centres.
        let (head, out) = (format!("{prefix}.head"), cfg.gaussians_per_voxel * RAW);
        let last = match cfg.head_hidden {
            0 => head,
            h => {
                linear_params(b, &format!("{head}.fc1"), w, h, true)?;
                format!("{head}.fc2")
            }
        };
        let fan_in = if cfg.head_hidden == 0 { w } else { cfg.head_hidden };
        b.add(&format!("{last}.w"), &[fan_in, out], Init::Normal { std: 0.01 })?;
        b.add(&format!("{last}.b"), &[out], Init::Zeros)
    }

    pub fn new(gpu: &Gpu, store: &ParamStore, prefix: &str, cfg: &GaussianConfig) -> Result<GaussianDecoder> {
        let mut blocks = Vec::new();
        for i in 0..cfg.blocks {
            let blk = format!("{prefix}.block{i}");
            let l = |p: &str| linear(store, &format!("{blk}.cross.{p}"), false);
            blocks.push(Block {
                norm_q: norm(store, &format!("{blk}.norm_q"))?,
                cross: MultiHeadAttention::new(l("q")?, l("k")?, l("v")?, l("o")?, cfg.heads)?,
                cross_ff: ff(store, &format!("{blk}.cross_ff"))?,
                layers: (0..cfg.self_layers)
                    .map(|s| WindowLayer::new(store, &format!("{blk}.self{s}"), cfg.heads, s % 2 == 1))
                    .collect::<Result<Vec<_>>>()?,
            });
        }
        Ok(GaussianDecoder {
            cfg: cfg.clone(),
            fourier_xyz: Fourier::octaves(gpu, 3, cfg.xyz_freqs, true)?,
            fourier_tau: Fourier::octaves(gpu, 1, cfg.tau_freqs, true)?,
            input: Dense::new(store, &format!("{prefix}.input"), cfg.input_hidden)?,
            blocks,
            head_norm: norm(store, &format!("{prefix}.head_norm"))?,
            head: Dense::new(store, &format!("{prefix}.head"), cfg.head_hidden)?,
        })
    }

    fn range(&self) -> HeadRange {
        HeadRange {
            offset_range: self.cfg.offset_range,
            scale_min: self.cfg.scale_min,
            scale_max: self.cfg.scale_max,
        }
    }

    /// Windows of `window_voxels`^3 voxels over the voxel centres; the fourth axis is the
    /// frame group, one cell each, so windows never mix the voxels of two frames.
    fn grid(&self, groups: usize) -> Result<WindowGrid> {
        let w = 2.0 * self.cfg.window_voxels as f32 / self.cfg.grid as f32;
        WindowGrid::new([-1.0, -1.0, -1.0, 0.0], [1.0, 1.0, 1.0, groups as f32], [w, w, w, 1.0])
    }

    /// Gaussians (`V x G` of them) for `centres` (f32 `[V, 3]`, occupied voxels) at frame `tau`
    /// from `tokens` (`[k, token_dim]`).
    pub fn forward(
        &self,
        rec: &mut Recorder,
        tokens: &Tensor,
        centres: &Tensor,
        tau: f32,
    ) -> Result<(Gaussians, GaussianCache)> {
        let v = centres.shape().first().copied().unwrap_or(0);
        let k = tokens.shape().first().copied().unwrap_or(0);
        let frames = VoxelFrames { groups: vec![(tau, v)], segments: Segments::dense(tokens.gpu(), v, k)? };
        self.forward_frames(rec, tokens, centres, &frames)
    }

    /// [`GaussianDecoder::forward`] of a batch: the voxels' frame times and tokens as `frames`
    /// says (the tokens of every sample of the batch, one after another).
    pub fn forward_frames(
        &self,
        rec: &mut Recorder,
        tokens: &Tensor,
        centres: &Tensor,
        frames: &VoxelFrames,
    ) -> Result<(Gaussians, GaussianCache)> {
        let v = match centres.shape() {
            &[v, 3] if v > 0 && centres.dtype() == DType::F32 => v,
            _ => {
                return Err(Error::Shape(format!(
                    "gaussian decoder: centres must be f32 [V > 0, 3], got {centres:?}"
                )))
            }
        };
        if tokens.shape().len() != 2 || tokens.shape()[0] == 0 {
            return Err(Error::Shape(format!(
                "gaussian decoder: tokens must be [k > 0, dim], got {tokens:?}"
            )));
        }
        if let Some(&(tau, _)) = frames.groups.iter().find(|g| !(g.0.is_finite() && g.0 >= 0.0)) {
            return Err(Error::Invalid(format!(
                "gaussian decoder: frame time {tau} must be finite and >= 0"
            )));
        }
        let counted: usize = frames.groups.iter().map(|g| g.1).sum();
        if counted != v {
            return Err(Error::Shape(format!(
                "gaussian decoder: the frame groups count {counted} voxels, the centres {v}"
            )));
        }
        let gpu = tokens.gpu().clone();
        // Query points (x, y, z, frame group) for the windows, and the query features.
        let per_voxel = |f: &dyn Fn(usize, f32) -> f32| -> Vec<f32> {
            frames
                .groups
                .iter()
                .enumerate()
                .flat_map(|(g, &(tau, n))| std::iter::repeat_n(f(g, tau), n))
                .collect()
        };
        let taus = Tensor::from_slice(&gpu, &[v, 1], &per_voxel(&|_, tau| tau))?;
        let group_ids = Tensor::from_slice(&gpu, &[v, 1], &per_voxel(&|g, _| g as f32))?;
        let points = Tensor::empty(&gpu, &[v, 4], DType::F32)?;
        copy_columns(rec, centres, 0, &points, 0, 3, 1.0)?;
        copy_columns(rec, &group_ids, 0, &points, 3, 1, 1.0)?;
        let grid = self.grid(frames.groups.len())?;
        let windows =
            [WindowLayout::new(rec, &points, &grid)?, WindowLayout::new(rec, &points, &grid.shifted())?];
        let (fx, _) = self.fourier_xyz.forward(rec, centres)?;
        let (ft, _) = self.fourier_tau.forward(rec, &taus)?;
        let (wx, wt) = (self.fourier_xyz.out_width(), self.fourier_tau.out_width());
        let features = Tensor::empty(&gpu, &[v, wx + wt], DType::F32)?;
        copy_columns(rec, &fx, 0, &features, 0, wx, 1.0)?;
        copy_columns(rec, &ft, 0, &features, wx, wt, 1.0)?;
        let (mut x, input) = self.input.forward(rec, &features)?;
        let cross_segments = frames.segments.clone();
        let mut blocks = Vec::new();
        for blk in &self.blocks {
            let (qn, norm_q) = blk.norm_q.forward(rec, &x)?;
            let (a, cross) = blk.cross.forward(rec, &qn, Some(tokens), &cross_segments)?;
            let x1 = binary(rec, &x, &a, Binary::Add)?;
            let (x2, cross_ff) = blk.cross_ff.forward(rec, &x1)?;
            x = x2;
            let mut layers = Vec::new();
            for layer in &blk.layers {
                let (x1, c) = layer.forward(rec, &x, &windows[layer.shifted as usize])?;
                x = x1;
                layers.push(c);
            }
            blocks.push(BlockCache { norm_q, cross, cross_ff, layers });
        }
        let (n, head_norm) = self.head_norm.forward(rec, &x)?;
        let (raw, head) = self.head.forward(rec, &n)?;
        let raw = raw.reshape(&[v * self.cfg.gaussians_per_voxel, RAW])?;
        let out = head_forward(rec, &raw, centres, &self.range())?;
        let cache = GaussianCache {
            centres: centres.clone(),
            windows,
            cross_segments,
            input,
            blocks,
            head_norm,
            head,
            raw,
            tokens_shape: tokens.shape().to_vec(),
        };
        Ok((out, cache))
    }

    /// Adds every parameter's gradient given the gradients of the Gaussians (the rasteriser's
    /// backward output); returns the gradient with respect to the tokens.
    pub fn backward(&self, rec: &mut Recorder, cache: &GaussianCache, d: &Gaussians) -> Result<Tensor> {
        let gpu = d.means.gpu().clone();
        let d_raw = head_backward(rec, &cache.raw, &cache.centres, &self.range(), d)?;
        let v = cache.centres.shape()[0];
        let d_raw = d_raw.reshape(&[v, self.cfg.gaussians_per_voxel * RAW])?;
        let dn = self.head.backward(rec, &cache.head, &d_raw)?;
        let mut dx = self.head_norm.backward(rec, &cache.head_norm, &dn)?;
        let d_tokens = Tensor::empty(&gpu, &cache.tokens_shape, DType::F32)?;
        fill(rec, &d_tokens, 0.0)?;
        for (blk, c) in self.blocks.iter().zip(&cache.blocks).rev() {
            for (layer, lc) in blk.layers.iter().zip(&c.layers).rev() {
                dx = layer.backward(rec, lc, &dx, &cache.windows[layer.shifted as usize])?;
            }
            let dx1 = blk.cross_ff.backward(rec, &c.cross_ff, &dx)?;
            let (dqn, dtok) = blk.cross.backward(rec, &c.cross, &dx1, &cache.cross_segments)?;
            let dq = blk.norm_q.backward(rec, &c.norm_q, &dqn)?;
            dx = binary(rec, &dx1, &dq, Binary::Add)?;
            let dtok = dtok.expect("cross-attention returns a context gradient");
            binary_into(rec, &d_tokens, &dtok, &d_tokens, Binary::Add)?;
        }
        self.input.param_grads(rec, &cache.input, &dx)?;
        Ok(d_tokens)
    }
}
