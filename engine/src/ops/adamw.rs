//! Fused AdamW over flat buffers, with global-norm gradient clipping. Kernel:
//! `shaders/adamw.wgsl`.
//!
//! One dispatch updates every parameter of a model when they live in one buffer (see the
//! parameter store in velox-models). Weight decay is decoupled (Loshchilov and Hutter) and
//! applies to the first `decay_len` elements only: the store lays out the tensors that decay
//! (weight matrices) before those that do not (norm gains, biases), so one push constant says
//! which is which and no mask buffer is needed.
//!
//! Clipping: with a norm buffer (the `[norm, ...]` result of [`crate::ops::norm`], recorded
//! earlier in the same command buffer), the kernel scales the gradient by
//! `min(1, max_norm / (grad_scale * norm + 1e-6))`, and skips the whole step when the norm is
//! NaN or Inf. Without one, gradients are used as they are (times `grad_scale`).
//!
//! Tests: the harness's `adamw` row (`engine/tests/ops/cases.rs`: forward against the f64 reference
//! at awkward shapes); `tests/training/train_primitives.rs` (chunked steps, clipping, a skipped
//! non-finite step, the store).

use crate::error::{Error, Result};
use crate::kernels::args;
use crate::kernels::ADAMW_MAIN;
use crate::ops::norm::{chunk_len, chunks};
use crate::recorder::Recorder;
use crate::tensor::{DType, Tensor};

/// The optimiser's fixed hyperparameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamWConfig {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Decoupled weight decay: each step multiplies decayed parameters by `1 - lr * weight_decay`.
    pub weight_decay: f64,
}

impl Default for AdamWConfig {
    /// beta1 0.9, beta2 0.999, eps 1e-8, weight decay 0.01.
    fn default() -> Self {
        AdamWConfig { beta1: 0.9, beta2: 0.999, eps: 1e-8, weight_decay: 0.01 }
    }
}

/// What changes from step to step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamWStep {
    /// Learning rate of this step (from a schedule).
    pub lr: f64,
    /// Step number, from 1; sets the bias corrections 1 - beta^step.
    pub step: u64,
    /// Multiplies every gradient before anything else (1 normally; 1/k to average k
    /// accumulated micro-batches, or to undo a loss scale).
    pub grad_scale: f64,
    /// Clip the scaled gradient to this global norm; `None` or a value <= 0 turns clipping off.
    /// Needs a norm buffer in [`AdamWTensors::norm`].
    pub max_norm: Option<f64>,
}

/// The flat buffers one AdamW dispatch updates, all f32 with the same number of elements.
pub struct AdamWTensors<'a> {
    pub params: &'a Tensor,
    pub grads: &'a Tensor,
    /// First moment, zero at the start.
    pub m: &'a Tensor,
    /// Second moment, zero at the start.
    pub v: &'a Tensor,
    /// Elements `[0, decay_len)` get weight decay, the rest do not.
    pub decay_len: usize,
    /// The global gradient norm in element 0 (from [`crate::ops::norm`]): clipping reads it and
    /// a NaN or Inf there skips the step.
    pub norm: Option<&'a Tensor>,
}

use crate::kernels::params::AdamwParams as Params;

/// Records one AdamW step over the flat buffers in `t`.
pub fn adamw(rec: &mut Recorder, t: &AdamWTensors, cfg: &AdamWConfig, step: &AdamWStep) -> Result<()> {
    adamw_chunked(rec, t, cfg, step, chunk_len(t.params.gpu()))
}

/// As [`adamw`], split into dispatches of at most `chunk` elements (a multiple of the view
/// alignment), so that tests can cover buffers larger than one binding on small sizes.
#[doc(hidden)]
pub fn adamw_chunked(
    rec: &mut Recorder,
    t: &AdamWTensors,
    cfg: &AdamWConfig,
    step: &AdamWStep,
    chunk: usize,
) -> Result<()> {
    let n = t.params.numel();
    for (what, x) in [("params", t.params), ("grads", t.grads), ("m", t.m), ("v", t.v)] {
        if x.dtype() != DType::F32 || x.numel() != n {
            return Err(Error::Shape(format!(
                "adamw: {what} is {x:?}, expected {n} f32 elements like the params {:?}",
                t.params
            )));
        }
    }
    if t.decay_len > n {
        return Err(Error::Shape(format!("adamw: decay_len {} past the {n} parameters", t.decay_len)));
    }
    if let Some(norm) = t.norm {
        if norm.dtype() != DType::F32 || norm.numel() == 0 {
            return Err(Error::Shape(format!("adamw: the norm buffer {norm:?} must be f32 with an element")));
        }
    }
    let max_norm = step.max_norm.unwrap_or(0.0);
    if max_norm > 0.0 && t.norm.is_none() {
        return Err(Error::Invalid("adamw: clipping to a max norm needs the gradient norm buffer".into()));
    }
    check_hyper(cfg, step)?;
    if chunk == 0 || !chunk.is_multiple_of(t.params.view_alignment()) {
        return Err(Error::Invalid(format!(
            "adamw: chunk of {chunk} elements is not a positive multiple of the view alignment {}",
            t.params.view_alignment()
        )));
    }
    let bias1 = 1.0 - cfg.beta1.powf(step.step as f64);
    let bias2 = 1.0 - cfg.beta2.powf(step.step as f64);
    let flat = |x: &Tensor| x.reshape(&[n]);
    let (p, g, m, v) = (flat(t.params)?, flat(t.grads)?, flat(t.m)?, flat(t.v)?);
    for (start, len) in chunks(n, chunk) {
        let params = Params {
            n: len as u32,
            decay_end: t.decay_len.saturating_sub(start).min(len) as u32,
            use_norm: t.norm.is_some() as u32,
            step: step.step.min(u32::MAX as u64) as u32,
            lr: step.lr as f32,
            beta1: cfg.beta1 as f32,
            one_minus_beta1: (1.0 - cfg.beta1) as f32,
            beta2: cfg.beta2 as f32,
            one_minus_beta2: (1.0 - cfg.beta2) as f32,
            eps: cfg.eps as f32,
            weight_decay: cfg.weight_decay as f32,
            grad_scale: step.grad_scale as f32,
            max_norm: max_norm.max(0.0) as f32,
            bias1: bias1 as f32,
            bias2: bias2 as f32,
        };
        let view = |x: &Tensor| x.view(start, &[len]);
        let (pv, gv, mv, vv) = (view(&p)?, view(&g)?, view(&m)?, view(&v)?);
        // Without a norm the kernel never reads binding 4; any bound buffer will do.
        let norm = t.norm.unwrap_or(&gv);
        rec.dispatch_linear(
            ADAMW_MAIN,
            (len as u64).div_ceil(256),
            args::AdamwMainArgs { param: &pv, grad: &gv, m: &mv, v: &vv, norm },
            &params,
        )?;
    }
    Ok(())
}

fn check_hyper(cfg: &AdamWConfig, step: &AdamWStep) -> Result<()> {
    let problem = if step.step == 0 {
        Some("step counts from 1".to_string())
    } else if !(0.0..1.0).contains(&cfg.beta1) || !(0.0..1.0).contains(&cfg.beta2) {
        Some(format!("betas {} and {} must lie in [0, 1)", cfg.beta1, cfg.beta2))
    } else if !(cfg.eps > 0.0 && cfg.eps.is_finite()) {
        Some(format!("eps {} must be positive", cfg.eps))
    } else if !(step.lr.is_finite() && step.lr >= 0.0) {
        Some(format!("learning rate {} must be finite and >= 0", step.lr))
    } else if !(cfg.weight_decay.is_finite() && cfg.weight_decay >= 0.0) {
        Some(format!("weight decay {} must be finite and >= 0", cfg.weight_decay))
    } else if !step.grad_scale.is_finite() {
        Some(format!("gradient scale {} must be finite", step.grad_scale))
    } else {
        None
    };
    match problem {
        Some(p) => Err(Error::Invalid(format!("adamw: {p}"))),
        None => Ok(()),
    }
}

pub mod reference {
    use super::{AdamWConfig, AdamWStep};

    /// One AdamW step in f64 on `p`, `m`, `v` with gradients `g`, as the kernel does it:
    /// `norm` is the global norm of `g` (clipping and the non-finite skip use it when given).
    /// Returns false when the step was skipped for a non-finite norm.
    #[allow(clippy::too_many_arguments)]
    pub fn adamw(
        p: &mut [f64],
        m: &mut [f64],
        v: &mut [f64],
        g: &[f32],
        decay_len: usize,
        norm: Option<f64>,
        cfg: &AdamWConfig,
        step: &AdamWStep,
    ) -> bool {
        let mut scale = step.grad_scale;
        if let Some(norm) = norm {
            if !norm.is_finite() {
                return false;
            }
            if let Some(max) = step.max_norm.filter(|&x| x > 0.0) {
                scale *= (max / (step.grad_scale.abs() * norm + 1e-6)).min(1.0);
            }
        }
        let t = step.step as f64;
        let bias1 = 1.0 - cfg.beta1.powf(t);
        let bias2 = 1.0 - cfg.beta2.powf(t);
        for i in 0..p.len() {
            let gi = g[i] as f64 * scale;
            m[i] = cfg.beta1 * m[i] + (1.0 - cfg.beta1) * gi;
            v[i] = cfg.beta2 * v[i] + (1.0 - cfg.beta2) * gi * gi;
            if i < decay_len {
                p[i] -= step.lr * cfg.weight_decay * p[i];
            }
            p[i] -= step.lr * (m[i] / bias1) / ((v[i] / bias2).sqrt() + cfg.eps);
        }
        true
    }
}
