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

use velox_engine::ops::attention::{attention, attention_backward, AttentionOut, Segments};
use velox_engine::ops::cast::cast;
use velox_engine::{DType, Error, Precision, Recorder, Result, Tensor};

use super::linear::{Linear, LinearCache};

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
}

pub struct MultiHeadAttentionCache {
    q_in: LinearCache,
    k_in: LinearCache,
    v_in: LinearCache,
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
        Ok(MultiHeadAttention { q, k, v, o, heads, head_dim: inner / heads })
    }

    fn scale(&self) -> f32 {
        1.0 / (self.head_dim as f32).sqrt()
    }

    fn split_heads(&self, t: &Tensor) -> Result<Tensor> {
        t.reshape(&[t.shape()[0], self.heads, self.head_dim])
    }

    /// `y [Nq, width]` for `x [Nq, width]` and, for cross-attention, `context [Nk, cwidth]`.
    pub fn forward(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        context: Option<&Tensor>,
        seg: &Segments,
    ) -> Result<(Tensor, MultiHeadAttentionCache)> {
        let c = context.unwrap_or(x);
        let (q, q_in) = self.q.forward(rec, x)?;
        let (k, k_in) = self.k.forward(rec, c)?;
        let (v, v_in) = self.v.forward(rec, c)?;
        let (q, k, v) = (self.split_heads(&q)?, self.split_heads(&k)?, self.split_heads(&v)?);
        // In an f16 recording the kernels read q, k and v rounded to f16, forward and backward.
        let (q, k, v) = match rec.precision() {
            Precision::F32 => (q, k, v),
            Precision::F16 => {
                (cast(rec, &q, DType::F16)?, cast(rec, &k, DType::F16)?, cast(rec, &v, DType::F16)?)
            }
        };
        let out = attention(rec, &q, &k, &v, seg, self.scale())?;
        let flat = out.o.reshape(&[out.o.shape()[0], self.heads * self.head_dim])?;
        let (y, o_in) = self.o.forward(rec, &flat)?;
        let cache = MultiHeadAttentionCache {
            q_in,
            k_in,
            v_in,
            o_in,
            q,
            k,
            v,
            out,
            self_attention: context.is_none(),
        };
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
        let d_flat = self.o.backward(rec, &cache.o_in, dy)?;
        let d_o = self.split_heads(&d_flat)?;
        let g = attention_backward(rec, &cache.q, &cache.k, &cache.v, &cache.out, &d_o, seg, self.scale())?;
        let flat = |t: &Tensor| t.reshape(&[t.shape()[0], self.heads * self.head_dim]);
        let (dq, dk, dv) = (flat(&g.dq)?, flat(&g.dk)?, flat(&g.dv)?);
        let gpu = dy.gpu();
        let dx = Tensor::empty(gpu, &[dq.shape()[0], self.q.in_features], DType::F32)?;
        self.q.grads_into(rec, &cache.q_in, &dq, &dx, false)?;
        // The context gradient, through k and v; for self-attention it adds into dx.
        let dc = if cache.self_attention {
            self.k.grads_into(rec, &cache.k_in, &dk, &dx, true)?;
            dx.clone()
        } else {
            let dc = Tensor::empty(gpu, &[dk.shape()[0], self.k.in_features], DType::F32)?;
            self.k.grads_into(rec, &cache.k_in, &dk, &dc, false)?;
            dc
        };
        self.v.grads_into(rec, &cache.v_in, &dv, &dc, true)?;
        Ok((dx, (!cache.self_attention).then_some(dc)))
    }
}
