//! Pieces the Velox models share: parameter declarations for linear layers, norms, attention
//! and feed-forwards, the pre-norm residual feed-forward, and self-attention within voxel
//! windows (tokens gathered into window order, attended per window, gathered back).
//!
//! Tests: through every model's step against finite differences (`tests/models/`), and the
//! weight-decay layout its helpers declare (`tests/models/slips.rs`).

use velox_engine::ops::attention::Segments;
use velox_engine::ops::gather::{gather, gather_plus, invert_permutation};
use velox_engine::ops::window::{group_by_window, window_ids, WindowGrid};
use velox_engine::{Recorder, Result, Tensor};

use velox_engine::ops::swiglu::silu_backward;
use velox_engine::ops::unary::{unary, Unary};

use crate::layers::attention::{MultiHeadAttention, MultiHeadAttentionCache};
use crate::layers::feedforward::SwiGluCache;
use crate::layers::linear::LinearCache;
use crate::layers::norm::RmsNormCache;
use crate::layers::Fourier;
use crate::layers::{GeluMlp, Linear, RmsNorm, SwiGlu};
use crate::params::{Init, Params};

pub const NORM_EPS: f32 = 1e-6;

/// A pre-norm residual feed-forward: `x + SwiGLU(RMSNorm(x))`.
pub struct FeedForward {
    pub norm: RmsNorm,
    pub ffn: SwiGlu,
}

/// A self-attention layer over voxel windows, then its feed-forward.
pub struct WindowLayer {
    pub norm: RmsNorm,
    pub attn: MultiHeadAttention,
    pub ff: FeedForward,
    /// Which of the two window layouts (plain, shifted) the layer uses.
    pub shifted: bool,
}

pub struct FeedForwardCache {
    norm: RmsNormCache,
    ffn: SwiGluCache,
}

pub struct WindowLayerCache {
    norm: RmsNormCache,
    attn: MultiHeadAttentionCache,
    ff: FeedForwardCache,
}

/// A linear layer `name.w [i, o]` (Xavier), with a bias `name.b [o]` (zeros) when `bias`.
pub fn linear(p: &mut Params, name: &str, i: usize, o: usize, bias: bool) -> Result<Linear> {
    let w = p.param(&format!("{name}.w"), &[i, o], Init::Xavier)?;
    let b = if bias { Some(p.param(&format!("{name}.b"), &[o], Init::Zeros)?) } else { None };
    Linear::new(w, b)
}

/// An RMS norm of `width` features, its gain `name` starting at one.
pub fn norm(p: &mut Params, name: &str, width: usize) -> Result<RmsNorm> {
    RmsNorm::new(p.param(name, &[width], Init::Ones)?, NORM_EPS)
}

/// Multi-head attention of `width` features attending to `context`-wide keys and values
/// (`name.q`, `.k`, `.v`, `.o`, no biases), with its projections stacked where they can be.
pub fn attention(
    p: &mut Params,
    name: &str,
    width: usize,
    context: usize,
    heads: usize,
) -> Result<MultiHeadAttention> {
    let mut l = |m: &str, i: usize| linear(p, &format!("{name}.{m}"), i, width, false);
    let (q, k, v, o) = (l("q", width)?, l("k", context)?, l("v", context)?, l("o", width)?);
    MultiHeadAttention::new(q, k, v, o, heads)?
        .with_stacks(p, ["q", "k", "v"].map(|m| format!("{name}.{m}.w")))
}

/// A GELU MLP `i -> hidden -> o` (`name.fc1`, `name.fc2`, each with a bias).
pub fn mlp(p: &mut Params, name: &str, i: usize, hidden: usize, o: usize) -> Result<GeluMlp> {
    let fc1 = linear(p, &format!("{name}.fc1"), i, hidden, true)?;
    let fc2 = linear(p, &format!("{name}.fc2"), hidden, o, true)?;
    GeluMlp::from_linears(fc1, fc2)
}

/// The pre-norm residual feed-forward of `width` features through `ratio * width` (`name.norm`,
/// `.w1`, `.w3`, `.w2`), its two input products stacked where they can be.
pub fn ff(p: &mut Params, name: &str, width: usize, ratio: usize) -> Result<FeedForward> {
    let norm = norm(p, &format!("{name}.norm"), width)?;
    let hidden = ratio * width;
    let mut w = |m: &str, i: usize, o: usize| p.param(&format!("{name}.{m}.w"), &[i, o], Init::Xavier);
    let (w1, w3, w2) = (w("w1", width, hidden)?, w("w3", width, hidden)?, w("w2", hidden, width)?);
    let ffn = SwiGlu::new(w1, w3, w2)?.with_stack(p, [&format!("{name}.w1.w"), &format!("{name}.w3.w")])?;
    Ok(FeedForward { norm, ffn })
}

impl FeedForward {
    /// `x + SwiGLU(RMSNorm(x))`.
    pub fn forward(&self, rec: &mut Recorder, x: &Tensor) -> Result<(Tensor, FeedForwardCache)> {
        let (n, norm) = self.norm.forward(rec, x)?;
        let (y, ffn) = self.ffn.forward_plus(rec, &n, x)?;
        Ok((y, FeedForwardCache { norm, ffn }))
    }

    /// `dx = dy + RMSNorm'(SwiGLU'(dy))` (the sum in the norm's pass).
    pub fn backward(&self, rec: &mut Recorder, cache: &FeedForwardCache, dy: &Tensor) -> Result<Tensor> {
        let dn = self.ffn.backward(rec, &cache.ffn, dy)?;
        self.norm.backward_plus(rec, &cache.norm, &dn, Some(dy))
    }
}

/// Tokens grouped by voxel window: the order that sorts them by window, its inverse, and the
/// segments of the occupied windows.
pub struct WindowLayout {
    pub order: Tensor,
    pub inverse: Tensor,
    pub segments: Segments,
}

impl WindowLayout {
    /// Groups tokens at `points` (f32 `[n, 4]`) by the windows of `grid`.
    pub fn new(rec: &mut Recorder, points: &Tensor, grid: &WindowGrid) -> Result<WindowLayout> {
        let ids = window_ids(rec, points, grid)?;
        WindowLayout::from_ids(rec, &ids, grid.num_windows())
    }

    /// Groups tokens by window id (u32 `[n]`, each below `num_windows`).
    pub fn from_ids(rec: &mut Recorder, ids: &Tensor, num_windows: u64) -> Result<WindowLayout> {
        let groups = group_by_window(rec, ids, num_windows)?;
        let inverse = invert_permutation(rec, &groups.order)?;
        // Every token is in the run of its window.
        let segments = Segments::covering_keys(groups.offsets.clone(), groups.offsets, ids.numel());
        Ok(WindowLayout { order: groups.order, inverse, segments })
    }
}

impl WindowLayer {
    /// The layer under `name` (`.norm`, `.attn`, `.ff`), on the `shifted` window layout or not.
    pub fn new(
        p: &mut Params,
        name: &str,
        width: usize,
        ratio: usize,
        heads: usize,
        shifted: bool,
    ) -> Result<WindowLayer> {
        Ok(WindowLayer {
            norm: norm(p, &format!("{name}.norm"), width)?,
            attn: attention(p, &format!("{name}.attn"), width, width, heads)?,
            ff: ff(p, &format!("{name}.ff"), width, ratio)?,
            shifted,
        })
    }

    /// `x + Attn_windows(RMSNorm(x))`, then the feed-forward.
    pub fn forward(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        w: &WindowLayout,
    ) -> Result<(Tensor, WindowLayerCache)> {
        let (n, norm) = self.norm.forward(rec, x)?;
        let n_sorted = gather(rec, &n, &w.order)?;
        let (a_sorted, attn) = self.attn.forward(rec, &n_sorted, None, &w.segments)?;
        let x1 = gather_plus(rec, &a_sorted, &w.inverse, x)?;
        let (y, ff) = self.ff.forward(rec, &x1)?;
        Ok((y, WindowLayerCache { norm, attn, ff }))
    }

    pub fn backward(
        &self,
        rec: &mut Recorder,
        cache: &WindowLayerCache,
        dy: &Tensor,
        w: &WindowLayout,
    ) -> Result<Tensor> {
        let dx1 = self.ff.backward(rec, &cache.ff, dy)?;
        // x1 = x + gather(a_sorted, inverse): the sorted gradient is dx1 gathered by order.
        let da_sorted = gather(rec, &dx1, &w.order)?;
        let (dn_sorted, _) = self.attn.backward(rec, &cache.attn, &da_sorted, &w.segments)?;
        let dn = gather(rec, &dn_sorted, &w.inverse)?;
        self.norm.backward_plus(rec, &cache.norm, &dn, Some(&dx1))
    }
}

/// The flow time's embedding of the adaLN networks (the surface decoder, the generator):
/// `e = silu(fc2(silu(fc1(Fourier(t)))))`, one row per time.
pub struct TimeEmbedding {
    pub fourier: Fourier,
    pub fc1: Linear,
    pub fc2: Linear,
}

/// The two pre-activations and the linears' inputs.
pub struct TimeEmbeddingCache {
    fc1: LinearCache,
    a1: Tensor,
    fc2: LinearCache,
    a2: Tensor,
}

impl TimeEmbedding {
    /// `e [n, width]` for the flow times `t` (`n` of them).
    pub fn forward(&self, rec: &mut Recorder, t: &Tensor) -> Result<(Tensor, TimeEmbeddingCache)> {
        let (ft, _) = self.fourier.forward(rec, &t.reshape(&[t.numel(), 1])?)?;
        let (a1, fc1) = self.fc1.forward(rec, &ft)?;
        let s1 = unary(rec, &a1, Unary::Silu)?;
        let (a2, fc2) = self.fc2.forward(rec, &s1)?;
        let e = unary(rec, &a2, Unary::Silu)?;
        Ok((e, TimeEmbeddingCache { fc1, a1, fc2, a2 }))
    }

    /// Adds the parameters' gradients for `de` (the times themselves get none).
    pub fn backward(&self, rec: &mut Recorder, cache: &TimeEmbeddingCache, de: &Tensor) -> Result<()> {
        let da2 = silu_backward(rec, &cache.a2, de)?;
        let ds1 = self.fc2.backward(rec, &cache.fc2, &da2)?;
        let da1 = silu_backward(rec, &cache.a1, &ds1)?;
        self.fc1.param_grads(rec, &cache.fc1, &da1)
    }
}
