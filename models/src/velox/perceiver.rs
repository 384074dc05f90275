//! A Perceiver over voxel queries, the trunk of the decoders that predict something per voxel
//! or per cell of a grid over [-1, 1]^3 from the dynamic tokens: the Gaussian decoder (per
//! occupied voxel, its Gaussians) and the voxel decoder's two stages (per coarse cell, its
//! occupancy).
//!
//! - Queries: points (x, y, z) in groups of one frame time each ([`VoxelFrames`]); each
//!   query's feature is its position, tau and their Fourier embeddings, through a linear layer
//!   or a GELU MLP (`input_hidden`).
//! - `blocks` Perceiver blocks, pre-norm RMSNorm, SwiGLU feed-forwards: cross-attention from the
//!   queries to the tokens of their sample (attention segments), then `self_layers`
//!   self-attention layers within windows of side `window` over the queries (every second one
//!   shifted by half a window; the frame group is the windows' fourth axis, one cell each, so
//!   no window mixes two frames).
//! - Head: RMSNorm, then a linear layer or a GELU MLP (`head_hidden`) to `out` numbers per
//!   query, its last layer initialised small (normal, `head_std`).
//!
//! The backward pass takes the gradient of the head's output and returns the tokens'.
//!
//! Tests: through the encoder's and the Gaussian decoder's (`tests/models/encoder.rs`,
//! `tests/models/gaussian_decoder.rs`).

use velox_engine::ops::attention::Segments;
use velox_engine::ops::columns::copy_columns;
use velox_engine::ops::fill::fill;
use velox_engine::ops::window::WindowGrid;
use velox_engine::{DType, Error, Gpu, Recorder, Result, Tensor};

use crate::layers::attention::{MultiHeadAttention, MultiHeadAttentionCache};
use crate::layers::feedforward::{GeluMlp, GeluMlpCache};
use crate::layers::linear::LinearCache;
use crate::layers::norm::RmsNormCache;
use crate::layers::{Fourier, Linear, RmsNorm};
use crate::params::{Init, Params};
use crate::velox::blocks::{
    attention, ff, linear, norm, FeedForward, FeedForwardCache, WindowLayer, WindowLayerCache, WindowLayout,
};

/// The sizes of a [`VoxelPerceiver`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PerceiverShape {
    pub width: usize,
    pub heads: usize,
    pub blocks: usize,
    pub self_layers: usize,
    pub ffn_ratio: usize,
    pub xyz_freqs: usize,
    pub tau_freqs: usize,
    /// Side of a self-attention window, in the [-1, 1] units of the query positions.
    pub window: f32,
    /// 0: a linear input layer; else a GELU MLP through this width.
    pub input_hidden: usize,
    /// 0: a linear head; else a GELU MLP through this width.
    pub head_hidden: usize,
    /// Numbers per query.
    pub out: usize,
    /// Standard deviation of the head's last weights.
    pub head_std: f64,
    /// Numbers a query brings beside its position (the tracker's query colour), which join
    /// its feature as they are: the query rows are `[x, y, z, features..]`.
    pub query_features: usize,
}

/// The frame groups of a batch of queries and the tokens each attends to: the queries are
/// `groups` in order, `(tau, count)` each, and `segments` gives each segment of queries (a
/// sample's frames) its rows of the tokens.
#[derive(Clone, Debug)]
pub struct VoxelFrames {
    pub groups: Vec<(f32, usize)>,
    pub segments: Segments,
}

impl VoxelFrames {
    /// `n` queries of one frame time, every one attending to all `k` tokens.
    pub fn single(gpu: &Gpu, tau: f32, n: usize, k: usize) -> Result<VoxelFrames> {
        Ok(VoxelFrames { groups: vec![(tau, n)], segments: Segments::dense(gpu, n, k)? })
    }
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
    /// `name` as a linear layer `i -> o` (no hidden width) or a GELU MLP `i -> hidden -> o`
    /// (`.fc1`, `.fc2`), each with a bias; the last layer's weights start from `last`, the
    /// others' from Xavier, the biases at zero.
    fn new(p: &mut Params, name: &str, i: usize, hidden: usize, o: usize, last: Init) -> Result<Dense> {
        let out = |p: &mut Params, name: &str, i: usize| {
            let w = p.param(&format!("{name}.w"), &[i, o], last)?;
            Linear::new(w, Some(p.param(&format!("{name}.b"), &[o], Init::Zeros)?))
        };
        Ok(match hidden {
            0 => Dense::Linear(out(p, name, i)?),
            h => {
                let fc1 = linear(p, &format!("{name}.fc1"), i, h, true)?;
                Dense::Mlp(GeluMlp::from_linears(fc1, out(p, &format!("{name}.fc2"), h)?)?)
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

struct Block {
    norm_q: RmsNorm,
    cross: MultiHeadAttention,
    cross_ff: FeedForward,
    layers: Vec<WindowLayer>,
}

struct BlockCache {
    norm_q: RmsNormCache,
    cross: MultiHeadAttentionCache,
    cross_ff: FeedForwardCache,
    layers: Vec<WindowLayerCache>,
}

pub struct VoxelPerceiver {
    pub shape: PerceiverShape,
    fourier_xyz: Fourier,
    fourier_tau: Fourier,
    input: Dense,
    blocks: Vec<Block>,
    head_norm: RmsNorm,
    head: Dense,
}

/// What [`VoxelPerceiver::backward`] needs from the forward pass.
pub struct PerceiverCache {
    /// The plain and the shifted windows; none without self-attention layers.
    windows: Vec<WindowLayout>,
    cross_segments: Segments,
    input: DenseCache,
    blocks: Vec<BlockCache>,
    head_norm: RmsNormCache,
    head: DenseCache,
    tokens_shape: Vec<usize>,
}

impl VoxelPerceiver {
    /// Width of a query's feature: position and its Fourier embedding, tau and its, then the
    /// query's own features.
    pub fn feature_width(shape: &PerceiverShape) -> usize {
        (3 + 6 * shape.xyz_freqs) + (1 + 2 * shape.tau_freqs) + shape.query_features
    }

    /// The perceiver, its parameters under `prefix` (`.input`, `.block{i}`, `.head_norm`,
    /// `.head`), attending to `token_dim`-wide tokens.
    pub fn new(
        p: &mut Params,
        prefix: &str,
        shape: &PerceiverShape,
        token_dim: usize,
    ) -> Result<VoxelPerceiver> {
        let w = shape.width;
        let gpu = p.gpu().clone();
        let input = Dense::new(
            p,
            &format!("{prefix}.input"),
            Self::feature_width(shape),
            shape.input_hidden,
            w,
            Init::Xavier,
        )?;
        let mut blocks = Vec::new();
        for i in 0..shape.blocks {
            let blk = format!("{prefix}.block{i}");
            blocks.push(Block {
                norm_q: norm(p, &format!("{blk}.norm_q"), w)?,
                cross: attention(p, &format!("{blk}.cross"), w, token_dim, shape.heads)?,
                cross_ff: ff(p, &format!("{blk}.cross_ff"), w, shape.ffn_ratio)?,
                layers: (0..shape.self_layers)
                    .map(|s| {
                        WindowLayer::new(
                            p,
                            &format!("{blk}.self{s}"),
                            w,
                            shape.ffn_ratio,
                            shape.heads,
                            s % 2 == 1,
                        )
                    })
                    .collect::<Result<Vec<_>>>()?,
            });
        }
        let head_norm = norm(p, &format!("{prefix}.head_norm"), w)?;
        let head_init = Init::Normal { std: shape.head_std };
        let head = Dense::new(p, &format!("{prefix}.head"), w, shape.head_hidden, shape.out, head_init)?;
        Ok(VoxelPerceiver {
            shape: *shape,
            fourier_xyz: Fourier::octaves(&gpu, 3, shape.xyz_freqs, true)?,
            fourier_tau: Fourier::octaves(&gpu, 1, shape.tau_freqs, true)?,
            input,
            blocks,
            head_norm,
            head,
        })
    }

    /// Windows of side `window` over the query positions; the fourth axis is the frame group,
    /// one cell each.
    fn grid(&self, groups: usize) -> Result<WindowGrid> {
        let w = self.shape.window;
        WindowGrid::new([-1.0, -1.0, -1.0, 0.0], [1.0, 1.0, 1.0, groups as f32], [w, w, w, 1.0])
    }

    /// `[V, out]` for the queries `positions` (f32 `[V, 3 + query_features]`: each one's
    /// position, then its features) of the frames `frames` from `tokens` (`[k, token_dim]`,
    /// every sample's one after another).
    pub fn forward(
        &self,
        rec: &mut Recorder,
        tokens: &Tensor,
        positions: &Tensor,
        frames: &VoxelFrames,
    ) -> Result<(Tensor, PerceiverCache)> {
        let extra = self.shape.query_features;
        let v = match positions.shape() {
            &[v, c] if v > 0 && c == 3 + extra && positions.dtype() == DType::F32 => v,
            _ => {
                let what = if extra > 0 { "position and features" } else { "position" };
                let want = 3 + extra;
                return Err(Error::Shape(format!(
                    "voxel perceiver: the query centres must be f32 [V > 0, {want}] ({what}), got {positions:?}"
                )));
            }
        };
        if tokens.shape().len() != 2 || tokens.shape()[0] == 0 {
            return Err(Error::Shape(format!(
                "voxel perceiver: tokens must be [k > 0, dim], got {tokens:?}"
            )));
        }
        if let Some(&(tau, _)) = frames.groups.iter().find(|g| !(g.0.is_finite() && g.0 >= 0.0)) {
            return Err(Error::Invalid(format!("voxel perceiver: frame time {tau} must be finite and >= 0")));
        }
        let counted: usize = frames.groups.iter().map(|g| g.1).sum();
        if counted != v {
            return Err(Error::Shape(format!(
                "voxel perceiver: the frame groups count {counted} queries, the positions {v}"
            )));
        }
        let gpu = tokens.gpu().clone();
        // Query points (x, y, z, frame group) for the windows, and the query features.
        let per_query = |f: &dyn Fn(usize, f32) -> f32| -> Vec<f32> {
            frames
                .groups
                .iter()
                .enumerate()
                .flat_map(|(g, &(tau, n))| std::iter::repeat_n(f(g, tau), n))
                .collect()
        };
        let taus = Tensor::from_slice(&gpu, &[v, 1], &per_query(&|_, tau| tau))?;
        let windows = if self.shape.self_layers == 0 {
            Vec::new()
        } else {
            let group_ids = Tensor::from_slice(&gpu, &[v, 1], &per_query(&|g, _| g as f32))?;
            let points = Tensor::empty(&gpu, &[v, 4], DType::F32)?;
            copy_columns(rec, positions, 0, &points, 0, 3, 1.0)?;
            copy_columns(rec, &group_ids, 0, &points, 3, 1, 1.0)?;
            let grid = self.grid(frames.groups.len())?;
            vec![WindowLayout::new(rec, &points, &grid)?, WindowLayout::new(rec, &points, &grid.shifted())?]
        };
        let xyz = if extra == 0 {
            positions.clone()
        } else {
            let xyz = Tensor::empty(&gpu, &[v, 3], DType::F32)?;
            copy_columns(rec, positions, 0, &xyz, 0, 3, 1.0)?;
            xyz
        };
        let (fx, _) = self.fourier_xyz.forward(rec, &xyz)?;
        let (ft, _) = self.fourier_tau.forward(rec, &taus)?;
        let (wx, wt) = (self.fourier_xyz.out_width(), self.fourier_tau.out_width());
        let features = Tensor::empty(&gpu, &[v, wx + wt + extra], DType::F32)?;
        copy_columns(rec, &fx, 0, &features, 0, wx, 1.0)?;
        copy_columns(rec, &ft, 0, &features, wx, wt, 1.0)?;
        if extra > 0 {
            copy_columns(rec, positions, 3, &features, wx + wt, extra, 1.0)?;
        }
        let (mut x, input) = self.input.forward(rec, &features)?;
        let cross_segments = frames.segments.clone();
        let mut blocks = Vec::new();
        for blk in &self.blocks {
            let (qn, norm_q) = blk.norm_q.forward(rec, &x)?;
            let (x1, cross) = blk.cross.forward_plus(rec, &qn, Some(tokens), &cross_segments, &x)?;
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
        let (out, head) = self.head.forward(rec, &n)?;
        let cache = PerceiverCache {
            windows,
            cross_segments,
            input,
            blocks,
            head_norm,
            head,
            tokens_shape: tokens.shape().to_vec(),
        };
        Ok((out, cache))
    }

    /// Adds every parameter's gradient given `d_out` (`[V, out]`); returns the gradient with
    /// respect to the tokens.
    pub fn backward(&self, rec: &mut Recorder, cache: &PerceiverCache, d_out: &Tensor) -> Result<Tensor> {
        let d_tokens = Tensor::empty(d_out.gpu(), &cache.tokens_shape, DType::F32)?;
        self.backward_into(rec, cache, d_out, &d_tokens, false)?;
        Ok(d_tokens)
    }

    /// [`VoxelPerceiver::backward`] with the tokens' gradient written into `d_tokens`, or added
    /// to what it holds (`accumulate`).
    pub fn backward_into(
        &self,
        rec: &mut Recorder,
        cache: &PerceiverCache,
        d_out: &Tensor,
        d_tokens: &Tensor,
        accumulate: bool,
    ) -> Result<()> {
        if d_tokens.shape() != cache.tokens_shape.as_slice() || d_tokens.dtype() != DType::F32 {
            return Err(Error::Shape(format!(
                "perceiver backward: the tokens' gradient must be f32 {:?}, got {d_tokens:?}",
                cache.tokens_shape
            )));
        }
        let dn = self.head.backward(rec, &cache.head, d_out)?;
        let mut dx = self.head_norm.backward(rec, &cache.head_norm, &dn)?;
        let mut started = accumulate;
        for (blk, c) in self.blocks.iter().zip(&cache.blocks).rev() {
            for (layer, lc) in blk.layers.iter().zip(&c.layers).rev() {
                dx = layer.backward(rec, lc, &dx, &cache.windows[layer.shifted as usize])?;
            }
            let dx1 = blk.cross_ff.backward(rec, &c.cross_ff, &dx)?;
            let dqn =
                blk.cross.backward_into(rec, &c.cross, &dx1, &cache.cross_segments, d_tokens, started)?;
            started = true;
            dx = blk.norm_q.backward_plus(rec, &c.norm_q, &dqn, Some(&dx1))?;
        }
        self.input.param_grads(rec, &cache.input, &dx)?;
        if !started {
            fill(rec, d_tokens, 0.0)?;
        }
        Ok(())
    }
}
