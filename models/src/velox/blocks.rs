//! Pieces the Velox models share: parameter declarations for linear layers, norms, attention
//! and feed-forwards, the pre-norm residual feed-forward, and self-attention within voxel
//! windows (tokens gathered into window order, attended per window, gathered back).

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
use crate::layers::{Linear, Param, RmsNorm, SwiGlu};
use crate::params::{Init, ParamBuilder, ParamStore};

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

pub fn linear_params(b: &mut ParamBuilder, name: &str, i: usize, o: usize, bias: bool) -> Result<()> {
    b.add(&format!("{name}.w"), &[i, o], Init::Xavier)?;
    if bias {
        b.add(&format!("{name}.b"), &[o], Init::Zeros)?;
    }
    Ok(())
}

pub fn linear(store: &ParamStore, name: &str, bias: bool) -> Result<Linear> {
    let b = if bias { Some(Param::from_store(store, &format!("{name}.b"))?) } else { None };
    Linear::new(Param::from_store(store, &format!("{name}.w"))?, b)
}

pub fn norm(store: &ParamStore, name: &str) -> Result<RmsNorm> {
    RmsNorm::new(Param::from_store(store, name)?, NORM_EPS)
}

pub fn attention_params(b: &mut ParamBuilder, name: &str, width: usize) -> Result<()> {
    for p in ["q", "k", "v", "o"] {
        linear_params(b, &format!("{name}.{p}"), width, width, false)?;
    }
    Ok(())
}

pub fn attention(store: &ParamStore, name: &str, heads: usize) -> Result<MultiHeadAttention> {
    let l = |p: &str| linear(store, &format!("{name}.{p}"), false);
    MultiHeadAttention::new(l("q")?, l("k")?, l("v")?, l("o")?, heads)?
        .with_store_stacks(store, ["q", "k", "v"].map(|p| format!("{name}.{p}.w")))
}

pub fn ff_params(b: &mut ParamBuilder, name: &str, width: usize, ratio: usize) -> Result<()> {
    b.add(&format!("{name}.norm"), &[width], Init::Ones)?;
    linear_params(b, &format!("{name}.w1"), width, ratio * width, false)?;
    linear_params(b, &format!("{name}.w3"), width, ratio * width, false)?;
    linear_params(b, &format!("{name}.w2"), ratio * width, width, false)
}

pub fn ff(store: &ParamStore, name: &str) -> Result<FeedForward> {
    let p = |s: &str| Param::from_store(store, &format!("{name}.{s}.w"));
    Ok(FeedForward {
        norm: norm(store, &format!("{name}.norm"))?,
        ffn: SwiGlu::new(p("w1")?, p("w3")?, p("w2")?)?
            .with_store_stack(store, [&format!("{name}.w1.w"), &format!("{name}.w3.w")])?,
    })
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

/// Declares a window layer's parameters under `name`.
pub fn window_layer_params(b: &mut ParamBuilder, name: &str, width: usize, ratio: usize) -> Result<()> {
    b.add(&format!("{name}.norm"), &[width], Init::Ones)?;
    attention_params(b, &format!("{name}.attn"), width)?;
    ff_params(b, &format!("{name}.ff"), width, ratio)
}

impl WindowLayer {
    pub fn new(store: &ParamStore, name: &str, heads: usize, shifted: bool) -> Result<WindowLayer> {
        Ok(WindowLayer {
            norm: norm(store, &format!("{name}.norm"))?,
            attn: attention(store, &format!("{name}.attn"), heads)?,
            ff: ff(store, &format!("{name}.ff"))?,
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
