//! Multi-head attention layer: projections around the engine's fused segment attention.
//!
//! `y = (softmax(q k^T / sqrt(d)) v) W_o` per segment and head, with `q = x W_q` and
//! `k = c W_k`, `v = c W_v`, where the context `c` is `x` itself (self-attention: the encoder's
//! voxel windows) or another token set (cross-attention: the encoder's cells, the decoders'
//! queries over the dynamic tokens). Which rows see which is given by
//! [`velox_engine::ops::attention::Segments`].
//!
//! Backward: `do = dy W_o^T`; the fused kernels give `dq, dk, dv`; `dx = dq W_q^T` (plus
//! `dk W_k^T + dv W_v^T` for self-attention), `dc = dk W_k^T + dv W_v^T` for cross-attention.
//!
//! In an f16 recording the projections run on f16 operands (see [`Linear::forward`]) and the
//! attention reads q, k, v rounded to f16, in the forward and the backward pass (mixed-precision
//! training); gradients, softmax statistics and outputs stay f32.
//!
//! Tests: `tests/models/attention_layer.rs` (multi-head attention against the reference, forward
//! and backward) and `tests/training/train_transformer.rs`.

use velox_engine::ops::attention::{
    attention, attention_backward_into, AttentionGrads, AttentionOut, Segments,
};
use velox_engine::ops::cast::cast;
use velox_engine::{DType, Error, Precision, Recorder, Result, Tensor};

use super::linear::{Linear, LinearCache, LinearStack};
use crate::params::Params;

pub struct MultiHeadAttention {
    /// `[width, heads * head_dim]`
    pub q: Linear,
    /// `[context width, heads * head_dim]`
    pub k: Linear,
    pub v: Linear,
    /// `[heads * head_dim, width]`
    pub o: Linear,
    pub heads: usize,
    pub head_dim: usize,
    /// The q, k and v projections as one stack (self-attention: one product for all three)
    /// and the k and v ones (cross-attention), where their parameters lie one after another
    /// in the store ([`MultiHeadAttention::with_stacks`]).
    qkv: Option<LinearStack>,
    kv: Option<LinearStack>,
}

/// What the projections kept of their inputs.
enum Projections {
    Separate {
        q: LinearCache,
        k: LinearCache,
        v: LinearCache,
    },
    /// q, k and v from one stacked product.
    Qkv(LinearCache),
    /// q alone, k and v from one stacked product.
    QandKv {
        q: LinearCache,
        kv: LinearCache,
    },
}

pub struct MultiHeadAttentionCache {
    projections: Projections,
    o_in: LinearCache,
    q: Tensor,
    k: Tensor,
    v: Tensor,
    out: AttentionOut,
    self_attention: bool,
}

impl MultiHeadAttention {
    pub fn new(q: Linear, k: Linear, v: Linear, o: Linear, heads: usize) -> Result<MultiHeadAttention> {
        let inner = q.out_features;
        if heads == 0 || !inner.is_multiple_of(heads) {
            return Err(Error::Shape(format!(
                "attention: {inner} projected features do not split into {heads} heads"
            )));
        }
        if k.out_features != inner || v.out_features != inner || o.in_features != inner {
            return Err(Error::Shape(format!(
                "attention: projections disagree: q -> {inner}, k -> {}, v -> {}, o <- {}",
                k.out_features, v.out_features, o.in_features
            )));
        }
        if k.in_features != v.in_features {
            return Err(Error::Shape("attention: k and v read contexts of different widths".into()));
        }
        Ok(MultiHeadAttention { q, k, v, o, heads, head_dim: inner / heads, qkv: None, kv: None })
    }

    /// Stacks the projections whose weights (`names`: q, k and v, without biases) lie one
    /// after another in the store: q, k, v for self-attention, k, v for cross-attention. Each
    /// stack saves the products and dispatches of the projections it joins.
    pub fn with_stacks<S: AsRef<str>>(
        mut self,
        params: &Params,
        names: [S; 3],
    ) -> Result<MultiHeadAttention> {
        if [&self.q, &self.k, &self.v].iter().any(|l| l.bias.is_some()) {
            return Ok(self);
        }
        if self.q.in_features == self.k.in_features {
            self.qkv = params.stacked(&names)?.map(|w| LinearStack::new(w, None)).transpose()?;
        }
        self.kv = params.stacked(&names[1..])?.map(|w| LinearStack::new(w, None)).transpose()?;
        Ok(self)
    }

    fn scale(&self) -> f32 {
        1.0 / (self.head_dim as f32).sqrt()
    }

    fn split_heads(&self, t: &Tensor) -> Result<Tensor> {
        t.reshape(&[t.shape()[0], self.heads, self.head_dim])
    }

    /// The projections' parts of a stacked `[N, rows, inner]` tensor, split into heads.
    fn heads_of<const N: usize>(&self, s: &LinearStack, all: &Tensor) -> Result<[Tensor; N]> {
        let parts = s.parts(all)?.iter().map(|p| self.split_heads(p)).collect::<Result<Vec<_>>>()?;
        Ok(parts.try_into().expect("a stack of as many projections as asked for"))
    }

    /// `y [Nq, width]` for `x [Nq, width]` and, for cross-attention, `context [Nk, cwidth]`.
    pub fn forward(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        context: Option<&Tensor>,
        seg: &Segments,
    ) -> Result<(Tensor, MultiHeadAttentionCache)> {
        self.forward_with(rec, x, context, seg, None)
    }

    /// `residual + y`, added by the output projection's product (a residual block's output
    /// without a separate add).
    pub fn forward_plus(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        context: Option<&Tensor>,
        seg: &Segments,
        residual: &Tensor,
    ) -> Result<(Tensor, MultiHeadAttentionCache)> {
        self.forward_with(rec, x, context, seg, Some(residual))
    }

    fn forward_with(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        context: Option<&Tensor>,
        seg: &Segments,
        residual: Option<&Tensor>,
    ) -> Result<(Tensor, MultiHeadAttentionCache)> {
        let c = context.unwrap_or(x);
        // In an f16 recording the kernels read q, k and v rounded to f16, forward and backward
        // (a stack's outputs rounded in one pass).
        let half = |rec: &mut Recorder, t: Tensor| match rec.precision() {
            Precision::F32 => Ok(t),
            Precision::F16 => cast(rec, &t, DType::F16),
        };
        let p = rec.precision();
        let (qkv, kv) =
            (self.qkv.as_ref().filter(|s| s.fits(x, p)), self.kv.as_ref().filter(|s| s.fits(c, p)));
        let (q, k, v, projections) = match (context, qkv, kv) {
            (None, Some(s), _) => {
                let (y, cache) = s.forward(rec, x)?;
                let y = half(rec, y)?;
                let [q, k, v] = self.heads_of(s, &y)?;
                (q, k, v, Projections::Qkv(cache))
            }
            (Some(_), _, Some(s)) => {
                let (q, q_in) = self.q.forward(rec, x)?;
                let q = half(rec, self.split_heads(&q)?)?;
                let (y, kv) = s.forward(rec, c)?;
                let y = half(rec, y)?;
                let [k, v] = self.heads_of(s, &y)?;
                (q, k, v, Projections::QandKv { q: q_in, kv })
            }
            _ => {
                let (q, q_in) = self.q.forward(rec, x)?;
                let (k, k_in) = self.k.forward(rec, c)?;
                let (v, v_in) = self.v.forward(rec, c)?;
                let q = half(rec, self.split_heads(&q)?)?;
                let k = half(rec, self.split_heads(&k)?)?;
                let v = half(rec, self.split_heads(&v)?)?;
                (q, k, v, Projections::Separate { q: q_in, k: k_in, v: v_in })
            }
        };
        let out = attention(rec, &q, &k, &v, seg, self.scale())?;
        let flat = out.o.reshape(&[out.o.shape()[0], self.heads * self.head_dim])?;
        let (y, o_in) = match residual {
            Some(r) => self.o.forward_plus(rec, &flat, r)?,
            None => self.o.forward(rec, &flat)?,
        };
        let cache =
            MultiHeadAttentionCache { projections, o_in, q, k, v, out, self_attention: context.is_none() };
        Ok((y, cache))
    }

    /// The keys and values `[Nk, heads, head_dim]` of a context, for a cross-attention whose
    /// context stays the same over many calls (a generator's condition over its sampling
    /// steps): computed once, then read by [`MultiHeadAttention::forward_kv`]. In an f16
    /// recording they are f16.
    pub fn context_kv(&self, rec: &mut Recorder, context: &Tensor) -> Result<(Tensor, Tensor)> {
        let (k, _) = self.k.forward(rec, context)?;
        let (v, _) = self.v.forward(rec, context)?;
        let (k, v) = (self.split_heads(&k)?, self.split_heads(&v)?);
        match rec.precision() {
            Precision::F32 => Ok((k, v)),
            Precision::F16 => Ok((cast(rec, &k, DType::F16)?, cast(rec, &v, DType::F16)?)),
        }
    }

    /// Cross-attention of `x [Nq, width]` to keys and values from
    /// [`MultiHeadAttention::context_kv`] (inference: nothing is kept for a backward pass).
    pub fn forward_kv(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        k: &Tensor,
        v: &Tensor,
        seg: &Segments,
    ) -> Result<Tensor> {
        let (q, _) = self.q.forward(rec, x)?;
        let q = self.split_heads(&q)?;
        let q = if k.dtype() == DType::F16 { cast(rec, &q, DType::F16)? } else { q };
        let out = attention(rec, &q, k, v, seg, self.scale())?;
        let flat = out.o.reshape(&[out.o.shape()[0], self.heads * self.head_dim])?;
        Ok(self.o.forward(rec, &flat)?.0)
    }

    /// Adds the projections' gradients; returns `dx` and, for cross-attention, `dcontext`.
    pub fn backward(
        &self,
        rec: &mut Recorder,
        cache: &MultiHeadAttentionCache,
        dy: &Tensor,
        seg: &Segments,
    ) -> Result<(Tensor, Option<Tensor>)> {
        self.backward_with(rec, cache, dy, seg, None)
    }

    /// The backward pass of a cross-attention with the context's gradient written into
    /// `dcontext` (`[Nk, cwidth]`), or added to what it holds (`accumulate`: a context several
    /// layers read); returns `dx`.
    pub fn backward_into(
        &self,
        rec: &mut Recorder,
        cache: &MultiHeadAttentionCache,
        dy: &Tensor,
        seg: &Segments,
        dcontext: &Tensor,
        accumulate: bool,
    ) -> Result<Tensor> {
        if cache.self_attention {
            return Err(Error::Shape("attention backward: a self-attention has no separate context".into()));
        }
        Ok(self.backward_with(rec, cache, dy, seg, Some((dcontext, accumulate)))?.0)
    }

    fn backward_with(
        &self,
        rec: &mut Recorder,
        cache: &MultiHeadAttentionCache,
        dy: &Tensor,
        seg: &Segments,
        dcontext: Option<(&Tensor, bool)>,
    ) -> Result<(Tensor, Option<Tensor>)> {
        let d_flat = self.o.backward(rec, &cache.o_in, dy)?;
        let d_o = self.split_heads(&d_flat)?;
        let gpu = dy.gpu();
        let (nq, nk) = (cache.q.shape()[0], cache.k.shape()[0]);
        let inner = self.heads * self.head_dim;
        let heads = |t: Tensor| t.reshape(&[t.shape()[0], self.heads, self.head_dim]);
        // The gradients of q, k and v where the projections' backward wants them: one
        // [3, n, inner] (or [2, nk, inner]) tensor for a stack.
        let (dq_all, dkv_all, grads) = match &cache.projections {
            Projections::Qkv(_) => {
                let s = self.qkv.as_ref().expect("a qkv cache comes from the stack");
                let all = Tensor::empty(gpu, &[3, nq, inner], DType::F32)?;
                let [dq, dk, dv] = self.heads_of(s, &all)?;
                (Some(all), None, AttentionGrads { dq, dk, dv })
            }
            Projections::QandKv { .. } => {
                let s = self.kv.as_ref().expect("a kv cache comes from the stack");
                let all = Tensor::empty(gpu, &[2, nk, inner], DType::F32)?;
                let [dk, dv] = self.heads_of(s, &all)?;
                let dq = heads(Tensor::empty(gpu, &[nq, inner], DType::F32)?)?;
                (None, Some(all), AttentionGrads { dq, dk, dv })
            }
            Projections::Separate { .. } => {
                let t = |n: usize| heads(Tensor::empty(gpu, &[n, inner], DType::F32)?);
                (None, None, AttentionGrads { dq: t(nq)?, dk: t(nk)?, dv: t(nk)? })
            }
        };
        attention_backward_into(
            rec,
            &cache.q,
            &cache.k,
            &cache.v,
            &cache.out,
            &d_o,
            seg,
            self.scale(),
            &grads,
        )?;
        let flat = |t: &Tensor| t.reshape(&[t.shape()[0], inner]);
        let (dq, dk, dv) = (flat(&grads.dq)?, flat(&grads.dk)?, flat(&grads.dv)?);
        let dx = Tensor::empty(gpu, &[nq, self.q.in_features], DType::F32)?;
        // Where the context's gradient goes: a new tensor, or the caller's.
        let context_out = |given: Option<(&Tensor, bool)>| -> Result<(Tensor, bool)> {
            match given {
                Some((t, accumulate)) => Ok((t.reshape(&[nk, self.k.in_features])?, accumulate)),
                None => Ok((Tensor::empty(gpu, &[nk, self.k.in_features], DType::F32)?, false)),
            }
        };
        let dc = match &cache.projections {
            Projections::Qkv(c) => {
                let s = self.qkv.as_ref().expect("a qkv cache comes from the stack");
                s.grads_into(rec, c, dq_all.as_ref().expect("stacked"), Some((&dx, false)))?;
                dx.clone()
            }
            Projections::QandKv { q, kv } => {
                self.q.grads_into(rec, q, &dq, &dx, false)?;
                let (dc, accumulate) = context_out(dcontext)?;
                let s = self.kv.as_ref().expect("a kv cache comes from the stack");
                s.grads_into(rec, kv, dkv_all.as_ref().expect("stacked"), Some((&dc, accumulate)))?;
                dc
            }
            Projections::Separate { q, k, v } => {
                self.q.grads_into(rec, q, &dq, &dx, false)?;
                // The context gradient, through k and v; for self-attention it adds into dx.
                let dc = if cache.self_attention {
                    self.k.grads_into(rec, k, &dk, &dx, true)?;
                    dx.clone()
                } else {
                    let (dc, accumulate) = context_out(dcontext)?;
                    self.k.grads_into(rec, k, &dk, &dc, accumulate)?;
                    dc
                };
                self.v.grads_into(rec, v, &dv, &dc, true)?;
                dc
            }
        };
        Ok((dx, (!cache.self_attention).then_some(dc)))
    }
}
