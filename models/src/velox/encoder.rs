//! The Velox encoder E (docs/models.md, Encoder; paper Sec. 3): a 4D colour point cloud to k
//! dynamic tokens.
//!
//! 1. Every point becomes an input token: Fourier(xyz) ++ rgb ++ Fourier(tau), then a linear
//!    layer to the model width.
//! 2. k queries: `oversample * k` random points, farthest point sampling in 4D down to k
//!    (distance over x, y, z, tau * time_scale); each query starts as its point's token.
//! 3. Every point joins the cell of its nearest query (computed once, reused by every block).
//! 4. Perceiver blocks, pre-norm RMSNorm, SwiGLU feed-forwards:
//!    - localized cross-attention: query c attends to the tokens of cell c only (a query with
//!      an empty cell gets zeros from the attention);
//!    - self-attention layers within 4D voxel windows over the query positions; every second
//!      layer shifts the windows by half a cell when `shift_windows` is set.
//! 5. RMSNorm and a linear layer to `token_dim`: the tokens s.
//!
//! FPS, the cells and the windows depend on the points only, not on the parameters, so the
//! encoder is a smooth function of its parameters and its backward pass goes through the
//! attention, the layers and the gathers alone. Tokens are reordered into window order (and
//! back) with gathers by a permutation and its inverse, which are exact.
//!
//! Tests: `tests/models/encoder.rs` (tokens, the backward against finite differences per tensor,
//! batches, bad clouds).

use velox_engine::ops::assign::assign_grouped;
use velox_engine::ops::attention::Segments;
use velox_engine::ops::columns::copy_columns;
use velox_engine::ops::concat::copy_add;
use velox_engine::ops::fill::fill;
use velox_engine::ops::fps::{fps, random_candidates};
use velox_engine::ops::gather::{gather, invert_permutation};
use velox_engine::ops::scatter_add::scatter_add;
use velox_engine::ops::window::{window_ids, WindowGrid};
use velox_engine::rng::Rng;
use velox_engine::{DType, Error, Recorder, Result, Tensor};

use crate::config::EncoderConfig;
use crate::layers::attention::{MultiHeadAttention, MultiHeadAttentionCache};
use crate::layers::fourier::FourierCache;
use crate::layers::linear::LinearCache;
use crate::layers::norm::RmsNormCache;
use crate::layers::{Fourier, Linear, RmsNorm};
use crate::params::Params;
use crate::velox::blocks::{
    attention, ff, linear, norm, FeedForward, FeedForwardCache, WindowLayer, WindowLayerCache, WindowLayout,
};
use velox_engine::{fit_u32, Limit};
use velox_io::cloud::CHANNELS;

/// Frames per clip and the frame rate of tau (docs/models.md): tau spans [0, 0.23].
pub const TAU_END: f32 = 0.24;

/// A Perceiver block: cell cross-attention and its feed-forward, then the window layers.
struct Block {
    norm_q: RmsNorm,
    norm_kv: RmsNorm,
    cross: MultiHeadAttention,
    cross_ff: FeedForward,
    layers: Vec<WindowLayer>,
}

pub struct Encoder {
    pub cfg: EncoderConfig,
    fourier_xyz: Fourier,
    fourier_tau: Fourier,
    input: Linear,
    blocks: Vec<Block>,
    out_norm: RmsNorm,
    out: Linear,
}

/// The grouping of one forward pass: which points the queries are, the cells, the windows.
pub struct Layout {
    /// Point index of every query, u32 `[k]`.
    pub queries: Tensor,
    /// Query positions (x, y, z, tau * time_scale), f32 `[k, 4]`.
    pub query_points: Tensor,
    /// Points in cell order, its inverse, and the cross-attention segments.
    cell_order: Tensor,
    cell_inverse: Tensor,
    cells: Segments,
    /// Plain and shifted windows over the queries.
    windows: [WindowLayout; 2],
    /// Clouds in the batch.
    pub batch: usize,
}

struct BlockCache {
    norm_q: RmsNormCache,
    norm_kv: RmsNormCache,
    cross: MultiHeadAttentionCache,
    cross_ff: FeedForwardCache,
    layers: Vec<WindowLayerCache>,
}

/// What the backward pass needs from the forward pass.
pub struct EncoderCache {
    pub layout: Layout,
    features: LinearCache,
    /// Input tokens in cell order, shared by every block's cross-attention.
    blocks: Vec<BlockCache>,
    out_norm: RmsNormCache,
    out: LinearCache,
    points: usize,
}

impl Encoder {
    /// Width of the input features: Fourier(xyz) with xyz, rgb, Fourier(tau) with tau.
    pub fn feature_width(cfg: &EncoderConfig) -> usize {
        (3 + 6 * cfg.xyz_freqs) + 3 + (1 + 2 * cfg.tau_freqs)
    }

    /// The encoder, its parameters under `prefix` (`.input`, `.block{i}`, `.out_norm`, `.out`).
    pub fn new(p: &mut Params, prefix: &str, cfg: &EncoderConfig) -> Result<Encoder> {
        let w = cfg.width;
        let gpu = p.gpu().clone();
        let input = linear(p, &format!("{prefix}.input"), Self::feature_width(cfg), w, true)?;
        let mut blocks = Vec::new();
        for i in 0..cfg.perceiver_blocks {
            let blk = format!("{prefix}.block{i}");
            blocks.push(Block {
                norm_q: norm(p, &format!("{blk}.norm_q"), w)?,
                norm_kv: norm(p, &format!("{blk}.norm_kv"), w)?,
                cross: attention(p, &format!("{blk}.cross"), w, w, cfg.heads)?,
                cross_ff: ff(p, &format!("{blk}.cross_ff"), w, cfg.ffn_ratio)?,
                layers: (0..cfg.self_layers)
                    .map(|l| {
                        let shifted = cfg.shift_windows && l % 2 == 1;
                        WindowLayer::new(p, &format!("{blk}.self{l}"), w, cfg.ffn_ratio, cfg.heads, shifted)
                    })
                    .collect::<Result<Vec<_>>>()?,
            });
        }
        Ok(Encoder {
            cfg: cfg.clone(),
            fourier_xyz: Fourier::log_spaced(&gpu, 3, cfg.xyz_freqs, cfg.xyz_max_octave, true)?,
            fourier_tau: Fourier::log_spaced(&gpu, 1, cfg.tau_freqs, cfg.tau_max_octave, true)?,
            input,
            blocks,
            out_norm: norm(p, &format!("{prefix}.out_norm"), w)?,
            out: linear(p, &format!("{prefix}.out"), w, cfg.token_dim, true)?,
        })
    }

    /// The voxel-window grid over (x, y, z, tau * time_scale).
    pub fn window_grid(&self) -> Result<WindowGrid> {
        let ts = self.cfg.time_scale;
        let w = self.cfg.window;
        WindowGrid::new([-1.0, -1.0, -1.0, 0.0], [1.0, 1.0, 1.0, TAU_END * ts], [w[0], w[1], w[2], w[3] * ts])
    }

    /// FPS queries, cells and windows for a cloud (`[N, 7]` on the device, validated).
    pub fn layout(&self, rec: &mut Recorder, cloud: &Tensor, rng: &mut Rng) -> Result<(Tensor, Layout)> {
        let (_, points, layout) = self.layout_batch(rec, &[cloud], std::slice::from_mut(rng))?;
        Ok((points, layout))
    }

    /// The layout of a batch of clouds (each `[N_b, 7]` on the device, validated), each drawing
    /// its queries from its own generator: returns the batch's cloud (the clouds one after
    /// another), its points `(x, y, z, tau * time_scale)` and the layout. Each cloud's queries,
    /// cells and windows are computed as for that cloud alone and shifted into the batch's
    /// numbering, so cells and windows never mix clouds, and cloud b's tokens are rows
    /// `b k .. (b + 1) k` of the output.
    pub fn layout_batch(
        &self,
        rec: &mut Recorder,
        clouds: &[&Tensor],
        rngs: &mut [Rng],
    ) -> Result<(Tensor, Tensor, Layout)> {
        let k = self.cfg.tokens;
        if clouds.is_empty() || clouds.len() != rngs.len() {
            return Err(Error::Invalid(format!(
                "the encoder needs one generator per cloud of a batch: {} clouds, {} generators",
                clouds.len(),
                rngs.len()
            )));
        }
        let sizes = clouds.iter().map(|c| check_cloud(c)).collect::<Result<Vec<_>>>()?;
        if let Some(n) = sizes.iter().find(|&&n| n < k) {
            return Err(Error::Invalid(format!(
                "the encoder needs at least {k} points for {k} tokens, a cloud has {n}"
            )));
        }
        let gpu = clouds[0].gpu().clone();
        let batch = clouds.len();
        let total: usize = sizes.iter().sum();
        let starts: Vec<usize> =
            sizes.iter().scan(0, |at, &n| Some(std::mem::replace(at, *at + n))).collect();
        let index = |v: usize| fit_u32(v, || format!("a batch of {total} points"));
        index(total)?;
        let rows_of = |rec: &mut Recorder, src: &Tensor, start: usize, rows: usize| -> Result<Tensor> {
            if start == 0 && rows == src.shape()[0] {
                return Ok(src.clone());
            }
            let mut shape = src.shape().to_vec();
            shape[0] = rows;
            let out = Tensor::empty(src.gpu(), &shape, src.dtype())?;
            rec.copy_rows(src, start, &out, 0, rows)?;
            Ok(out)
        };
        let cloud = if batch == 1 {
            clouds[0].clone()
        } else {
            let all = Tensor::empty(&gpu, &[total, CHANNELS], DType::F32)?;
            for (c, &at) in clouds.iter().zip(&starts) {
                rec.copy_rows(c, 0, &all, at, c.shape()[0])?;
            }
            all
        };
        let points = Tensor::empty(&gpu, &[total, 4], DType::F32)?;
        copy_columns(rec, &cloud, 0, &points, 0, 3, 1.0)?;
        copy_columns(rec, &cloud, 6, &points, 3, 1, self.cfg.time_scale)?;

        // Queries: FPS within each cloud.
        let queries = Tensor::empty(&gpu, &[batch * k], DType::U32)?;
        let mut cloud_points = Vec::with_capacity(batch);
        for ((&n, &at), (b, rng)) in sizes.iter().zip(&starts).zip(rngs.iter_mut().enumerate()) {
            let pts = rows_of(rec, &points, at, n)?;
            let candidates = random_candidates(n, k.saturating_mul(self.cfg.oversample), rng)?;
            let q = fps(rec, &pts, &candidates, k)?;
            copy_add(rec, &q, 0, &queries, b * k, k, index(at)?)?;
            cloud_points.push(pts);
        }
        let query_points = gather(rec, &points, &queries)?;

        // Cells and windows within each cloud, shifted into the batch's numbering.
        let cell_order = Tensor::empty(&gpu, &[total], DType::U32)?;
        let cell_offsets = Tensor::from_slice(&gpu, &[batch * k + 1], &vec![0u32; batch * k + 1])?;
        let grids = [self.window_grid()?, self.window_grid()?.shifted()];
        let window_ids_all =
            [Tensor::empty(&gpu, &[batch * k], DType::U32)?, Tensor::empty(&gpu, &[batch * k], DType::U32)?];
        for (b, (pts, &at)) in cloud_points.iter().zip(&starts).enumerate() {
            let qp = rows_of(rec, &query_points, b * k, k)?;
            let cells = assign_grouped(rec, pts, &qp)?;
            copy_add(rec, &cells.order, 0, &cell_order, at, pts.shape()[0], index(at)?)?;
            copy_add(rec, &cells.offsets, 1, &cell_offsets, b * k + 1, k, index(at)?)?;
            for (grid, ids) in grids.iter().zip(&window_ids_all) {
                let shift = u32::try_from(b as u64 * grid.num_windows()).map_err(|_| {
                    Error::too_large(
                        Limit::Index,
                        format!("{batch} clouds of {} windows", grid.num_windows()),
                    )
                })?;
                let local = window_ids(rec, &qp, grid)?;
                copy_add(rec, &local, 0, ids, b * k, k, shift)?;
            }
        }
        let cell_inverse = invert_permutation(rec, &cell_order)?;
        let one_each: Vec<u32> = (0..=(batch * k) as u32).collect();
        // Every point of every cloud is in its nearest query's cell.
        let q_offsets = Tensor::from_slice(&gpu, &[batch * k + 1], &one_each)?;
        let cells = Segments::covering_keys(q_offsets, cell_offsets, total);
        let windows = [
            WindowLayout::from_ids(rec, &window_ids_all[0], batch as u64 * grids[0].num_windows())?,
            WindowLayout::from_ids(rec, &window_ids_all[1], batch as u64 * grids[1].num_windows())?,
        ];
        let layout = Layout { queries, query_points, cell_order, cell_inverse, cells, windows, batch };
        Ok((cloud, points, layout))
    }

    /// Input tokens `[N, width]` from the cloud.
    fn input_tokens(&self, rec: &mut Recorder, cloud: &Tensor) -> Result<(Tensor, LinearCache)> {
        let n = cloud.shape()[0];
        let gpu = cloud.gpu().clone();
        let xyz = Tensor::empty(&gpu, &[n, 3], DType::F32)?;
        copy_columns(rec, cloud, 0, &xyz, 0, 3, 1.0)?;
        let tau = Tensor::empty(&gpu, &[n, 1], DType::F32)?;
        copy_columns(rec, cloud, 6, &tau, 0, 1, 1.0)?;
        let (fx, _): (Tensor, FourierCache) = self.fourier_xyz.forward(rec, &xyz)?;
        let (ft, _) = self.fourier_tau.forward(rec, &tau)?;
        let (wx, wt) = (self.fourier_xyz.out_width(), self.fourier_tau.out_width());
        let features = Tensor::empty(&gpu, &[n, wx + 3 + wt], DType::F32)?;
        copy_columns(rec, &fx, 0, &features, 0, wx, 1.0)?;
        copy_columns(rec, cloud, 3, &features, wx, 3, 1.0)?;
        copy_columns(rec, &ft, 0, &features, wx + 3, wt, 1.0)?;
        self.input.forward(rec, &features)
    }

    /// Tokens s `[k, token_dim]` of a cloud, and what the backward pass needs. The queries and
    /// the FPS start come from `rng`.
    pub fn forward(
        &self,
        rec: &mut Recorder,
        cloud: &Tensor,
        rng: &mut Rng,
    ) -> Result<(Tensor, EncoderCache)> {
        self.forward_batch(rec, &[cloud], std::slice::from_mut(rng))
    }

    /// Tokens `[B k, token_dim]` of a batch of clouds (cloud b's are rows `b k .. (b + 1) k`),
    /// each drawing its queries from its own generator; see [`Encoder::layout_batch`].
    pub fn forward_batch(
        &self,
        rec: &mut Recorder,
        clouds: &[&Tensor],
        rngs: &mut [Rng],
    ) -> Result<(Tensor, EncoderCache)> {
        let (cloud, _, layout) = self.layout_batch(rec, clouds, rngs)?;
        self.forward_with(rec, &cloud, layout)
    }

    /// The forward pass over a layout computed before (the same cloud).
    pub fn forward_with(
        &self,
        rec: &mut Recorder,
        cloud: &Tensor,
        layout: Layout,
    ) -> Result<(Tensor, EncoderCache)> {
        let points = check_cloud(cloud)?;
        let (tokens, features) = self.input_tokens(rec, cloud)?;
        let kv = gather(rec, &tokens, &layout.cell_order)?;
        let mut q = gather(rec, &tokens, &layout.queries)?;
        let mut blocks = Vec::new();
        for blk in &self.blocks {
            let (qn, norm_q) = blk.norm_q.forward(rec, &q)?;
            let (kvn, norm_kv) = blk.norm_kv.forward(rec, &kv)?;
            let (q1, cross) = blk.cross.forward_plus(rec, &qn, Some(&kvn), &layout.cells, &q)?;
            let (q2, cross_ff) = blk.cross_ff.forward(rec, &q1)?;
            q = q2;
            let mut layers = Vec::new();
            for layer in &blk.layers {
                let (q1, c) = layer.forward(rec, &q, &layout.windows[layer.shifted as usize])?;
                q = q1;
                layers.push(c);
            }
            blocks.push(BlockCache { norm_q, norm_kv, cross, cross_ff, layers });
        }
        let (n, out_norm) = self.out_norm.forward(rec, &q)?;
        let (s, out) = self.out.forward(rec, &n)?;
        Ok((s, EncoderCache { layout, features, blocks, out_norm, out, points }))
    }

    /// Adds every parameter's gradient for `ds = dL/ds`.
    pub fn backward(&self, rec: &mut Recorder, cache: &EncoderCache, ds: &Tensor) -> Result<()> {
        let layout = &cache.layout;
        let gpu = ds.gpu().clone();
        let dn = self.out.backward(rec, &cache.out, ds)?;
        let mut dq = self.out_norm.backward(rec, &cache.out_norm, &dn)?;
        // Gradient of the cell-ordered input tokens, summed over the blocks.
        let mut dkv: Option<Tensor> = None;
        for (blk, c) in self.blocks.iter().zip(&cache.blocks).rev() {
            for (layer, lc) in blk.layers.iter().zip(&c.layers).rev() {
                dq = layer.backward(rec, lc, &dq, &layout.windows[layer.shifted as usize])?;
            }
            let dq1 = blk.cross_ff.backward(rec, &c.cross_ff, &dq)?;
            let (dqn, dkvn) = blk.cross.backward(rec, &c.cross, &dq1, &layout.cells)?;
            let dkvn = dkvn.expect("cross-attention returns a context gradient");
            dq = blk.norm_q.backward_plus(rec, &c.norm_q, &dqn, Some(&dq1))?;
            dkv = Some(blk.norm_kv.backward_plus(rec, &c.norm_kv, &dkvn, dkv.as_ref())?);
        }
        let dkv = match dkv {
            Some(d) => d,
            None => {
                let d = Tensor::empty(&gpu, &[cache.points, self.cfg.width], DType::F32)?;
                fill(rec, &d, 0.0)?;
                d
            }
        };
        // Input tokens: through the cell order (a permutation) and the query gather. FPS never
        // picks a point twice, so each row of the scatter takes one addition: the same bits on
        // every run.
        let dtokens = gather(rec, &dkv, &layout.cell_inverse)?;
        scatter_add(rec, &dq, &layout.queries, &dtokens)?;
        self.input.param_grads(rec, &cache.features, &dtokens)
    }
}

fn check_cloud(cloud: &Tensor) -> Result<usize> {
    match (cloud.dtype(), cloud.shape()) {
        (DType::F32, &[n, c]) if c == CHANNELS && n > 0 => Ok(n),
        _ => Err(Error::Shape(format!(
            "the encoder reads a cloud of f32 [N, {CHANNELS}] (x, y, z, r, g, b, tau) with N > 0, got {cloud:?}"
        ))),
    }
}
