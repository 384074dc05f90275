//! The 4D surface decoder V (docs/models.md, "4D surface decoder V"; paper Sec. 3, "Learning
//! geometry"): a rectified-flow velocity network over points, conditioned on the dynamic tokens.
//!
//! Training (rectified flow): for points `x` of one frame time `tau`, noise `eps ~ N(0, I)` and
//! flow times `t` uniform in `[t_min, 1 - t_min]`, the network sees `x_t = t x + (1 - t) eps`
//! and is asked for the velocity `u = x - eps`; `L_V = mean |v - u|^2` (mean over points and
//! coordinates). Sampling integrates `v` from `t = 0` (`x_0 ~ N(0, I)`) to `t = 1` with Euler
//! or Heun steps.
//!
//! The network, per point (points never see each other):
//! ```text
//! h = [x_t ++ Fourier(x_t) ++ Fourier(tau)] W_in + b_in
//! e = silu(MLP(Fourier(t)))                         time embedding, [time_embed]
//! each block:  h += gate_a * CrossAttn(LN(h) * (1 + scale_a) + shift_a, tokens)
//!              h += gate_m * GeluMlp(LN(h) * (1 + scale_m) + shift_m)
//! v = (LN(h) * (1 + scale_f) + shift_f) W_out + b_out
//! ```
//! where every shift, scale and gate is a linear map of `e` (adaLN-Zero: those maps and `W_out`
//! start at zero, so the untrained network outputs 0). The maps are one `Linear` per role,
//! which is the paper's single `time_embed -> 6 x width` linear split by its output columns.
//! `W_in` is stored as two parameters, the rows that read the point's features and those that
//! read `Fourier(tau)`: tau is one number per call, so its rows give one `[1, width]` row added
//! to every point.
//!
//! Each point has its own `t` in training, so the modulation is per point (`Modulate` with
//! `B = points, T = 1`); in sampling every point shares one `t`, and the modulation is computed
//! once (`B = 1, T = points`).
//!
//! Tests: `tests/models/surface_decoder.rs` (the backward against finite differences, independent
//! points, overfitting a shape, Heun's exactness), `tests/models/slips.rs` (the flow noise reaching
//! input, target and time).

use velox_engine::ops::attention::Segments;
use velox_engine::ops::binary::{binary, binary_into, Binary};
use velox_engine::ops::fill::fill;
use velox_engine::ops::reduce::{reduce, Reduce};
use velox_engine::ops::unary::{unary, Unary};
use velox_engine::rng::Rng;
use velox_engine::{DType, Error, Gpu, Precision, Recorder, Result, Tensor};

use crate::config::SurfaceConfig;
use crate::layers::adaln::{GatedResidualCache, ModulateCache};
use crate::layers::attention::MultiHeadAttentionCache;
use crate::layers::feedforward::GeluMlpCache;
use crate::layers::linear::{LinearCache, LinearStack};
use crate::layers::norm::LayerNormCache;
use crate::layers::{Fourier, GatedResidual, GeluMlp, LayerNorm, Linear, Loss, Modulate, MultiHeadAttention};
use crate::params::{build, Init, ParamStore, Params};
use crate::velox::blocks::{attention, linear, mlp, TimeEmbedding, TimeEmbeddingCache};

/// LayerNorm epsilon under adaLN (DiT's value).
const LN_EPS: f32 = 1e-6;
/// The largest activation one sampling chunk may hold, in bytes: a quarter of the device's
/// largest storage binding, within these bounds (lavapipe binds 128 MiB, so 32 MiB there; an
/// H100 binds 4 GiB, so 256 MiB: 16384 points of the paper's width in one chunk, whose
/// attention has 4x the work items of a 4096-point chunk to spread over the GPU).
const SAMPLE_CHUNK_BYTES: (u64, u64) = (32 << 20, 256 << 20);

/// The six modulation roles of a block, in the order of the paper's `6 x width` output.
const BLOCK_ROLES: [&str; 6] =
    ["shift_attn", "scale_attn", "gate_attn", "shift_mlp", "scale_mlp", "gate_mlp"];
/// The final layer's two.
const FINAL_ROLES: [&str; 2] = ["shift", "scale"];

/// Widths of the input features.
fn feature_widths(cfg: &SurfaceConfig) -> (usize, usize, usize) {
    let xyz = 3 + 3 * 2 * cfg.xyz_freqs;
    let tau = 2 * cfg.tau_freqs;
    let time = 1 + 2 * cfg.time_freqs;
    (xyz, tau, time)
}

fn check_config(cfg: &SurfaceConfig, token_dim: usize) -> Result<()> {
    if cfg.width == 0 || cfg.heads == 0 || !cfg.width.is_multiple_of(cfg.heads) {
        return Err(Error::Invalid(format!(
            "surface decoder: width {} does not split into {} heads",
            cfg.width, cfg.heads
        )));
    }
    let d = cfg.width / cfg.heads;
    if !velox_engine::ops::attention::HEAD_DIMS.contains(&d) {
        return Err(Error::Invalid(format!(
            "surface decoder: head width {d} has no attention kernel (compiled: {:?})",
            velox_engine::ops::attention::HEAD_DIMS
        )));
    }
    if cfg.mlp_ratio == 0 || cfg.time_embed == 0 || token_dim == 0 {
        return Err(Error::Invalid(format!(
            "surface decoder: mlp_ratio {}, time_embed {} and token_dim {token_dim} must be positive",
            cfg.mlp_ratio, cfg.time_embed
        )));
    }
    if !(cfg.t_min.is_finite() && (0.0..0.5).contains(&cfg.t_min)) {
        return Err(Error::Invalid(format!("surface decoder: t_min {} must lie in [0, 0.5)", cfg.t_min)));
    }
    Ok(())
}

/// The adaLN-modulated cross-attention and MLP of one block.
struct Block {
    attn: MultiHeadAttention,
    mlp: GeluMlp,
    /// `BLOCK_ROLES`, each `time_embed -> width`.
    adaln: Modulation,
}

/// The adaLN linears of a block or of the final layer, which all read the time embedding:
/// one stacked product where the store holds their parameters one after another (it does as
/// the decoder registers them), the linears one by one otherwise.
struct Modulation {
    linears: Vec<Linear>,
    stack: Option<LinearStack>,
}

impl Modulation {
    /// The linears `bases[i]` (`.w [input, width]`, `.b [width]`), all starting at zero.
    fn new(p: &mut Params, bases: &[String], input: usize, width: usize) -> Result<Modulation> {
        let linears = bases
            .iter()
            .map(|base| {
                let w = p.param(&format!("{base}.w"), &[input, width], Init::Zeros)?;
                Linear::new(w, Some(p.param(&format!("{base}.b"), &[width], Init::Zeros)?))
            })
            .collect::<Result<Vec<_>>>()?;
        let names = |suffix: &str| bases.iter().map(|b| format!("{b}.{suffix}")).collect::<Vec<_>>();
        let stack = match (p.stacked(&names("w"))?, p.stacked(&names("b"))?) {
            (Some(w), Some(b)) => Some(LinearStack::new(w, Some(b))?),
            _ => None,
        };
        Ok(Modulation { linears, stack })
    }

    /// The stack, where its output over `e`'s rows splits into views in `rec`'s precision.
    fn stack_for(&self, rec: &Recorder, e: &Tensor) -> Option<&LinearStack> {
        self.stack.as_ref().filter(|s| s.fits(e, rec.precision()))
    }

    /// Each linear's output `[rows, width]` for the time embedding `e [rows, time_embed]`;
    /// `e_cache` keeps what the backward pass needs of `e` (once for every modulation).
    fn forward(
        &self,
        rec: &mut Recorder,
        e: &Tensor,
        e_cache: &mut Option<LinearCache>,
    ) -> Result<Vec<Tensor>> {
        let Some(s) = self.stack_for(rec, e) else {
            return self
                .linears
                .iter()
                .map(|l| {
                    let (m, c) = l.forward(rec, e)?;
                    e_cache.get_or_insert(c);
                    Ok(m)
                })
                .collect();
        };
        let (y, c) = s.forward(rec, e)?;
        e_cache.get_or_insert(c);
        s.parts(&y)
    }

    /// Adds the gradients for `dm` (one per linear, `[rows, width]`) and adds their input
    /// gradient into `de` (writes it when `*de_started` is false, then sets it).
    fn backward(
        &self,
        rec: &mut Recorder,
        e_cache: &LinearCache,
        dm: &[&Tensor],
        de: &Tensor,
        de_started: &mut bool,
    ) -> Result<()> {
        match self.stack_for(rec, de) {
            Some(s) => {
                let rows = de.numel() / s.in_features;
                let all = Tensor::empty(de.gpu(), &[s.k, rows, s.out_features], DType::F32)?;
                for (d, part) in dm.iter().zip(s.parts(&all)?) {
                    rec.copy(d, &part)?;
                }
                s.grads_into(rec, e_cache, &all, Some((de, *de_started)))?;
            }
            None => {
                for (l, d) in self.linears.iter().zip(dm) {
                    l.grads_into(rec, e_cache, d, de, *de_started)?;
                    *de_started = true;
                }
            }
        }
        *de_started = true;
        Ok(())
    }
}

pub struct SurfaceDecoder {
    pub cfg: SurfaceConfig,
    pub token_dim: usize,
    xyz_fourier: Fourier,
    tau_fourier: Option<Fourier>,
    /// The rows of the input linear that read `x_t ++ Fourier(x_t)` (with the bias), and those
    /// that read `Fourier(tau)`.
    input: Linear,
    input_tau: Option<Linear>,
    time: TimeEmbedding,
    blocks: Vec<Block>,
    final_adaln: Modulation,
    out: Linear,
    norm: LayerNorm,
}

struct BlockCache {
    ln1: LayerNormCache,
    mod1: ModulateCache,
    attn: MultiHeadAttentionCache,
    res1: GatedResidualCache,
    ln2: LayerNormCache,
    mod2: ModulateCache,
    mlp: GeluMlpCache,
    res2: GatedResidualCache,
}

/// What [`SurfaceDecoder::backward`] needs from the forward pass.
pub struct SurfaceCache {
    n: usize,
    /// Frame-time groups of the points.
    groups: usize,
    /// The modulation batch: `(B, T)` = `(points, 1)` with per-point `t`, `(1, points)` shared.
    b: usize,
    tt: usize,
    k: usize,
    seg: Segments,
    time: TimeEmbeddingCache,
    /// The time embedding `e`, as the modulations read it.
    e: LinearCache,
    input: LinearCache,
    input_tau: Option<LinearCache>,
    blocks: Vec<BlockCache>,
    ln_final: LayerNormCache,
    mod_final: ModulateCache,
    out: LinearCache,
}

/// The frame times of a batch of points and the tokens each attends to: the points are
/// `taus.len()` equal groups in order, group g at frame time `taus[g]`, and `segments` gives
/// each segment of points (a sample's groups) its rows of the tokens.
#[derive(Clone, Debug)]
pub struct PointFrames {
    pub taus: Vec<f32>,
    pub segments: Segments,
}

impl PointFrames {
    /// `n` points of one frame time, every one attending to all `k` tokens.
    pub fn single(gpu: &Gpu, tau: f32, n: usize, k: usize) -> Result<PointFrames> {
        Ok(PointFrames { taus: vec![tau], segments: Segments::dense(gpu, n, k)? })
    }
}

/// The noise of one rectified-flow step: `eps [N, 3]` and per-point flow times `t [N]`.
pub struct FlowNoise {
    pub eps: Tensor,
    pub t: Tensor,
}

impl FlowNoise {
    /// `eps ~ N(0, I)` and `t` uniform in `[t_min, 1 - t_min]`, drawn on the host from `rng`.
    pub fn draw(gpu: &Gpu, points: usize, t_min: f32, rng: &mut Rng) -> Result<FlowNoise> {
        let eps = rng.normal_vec(points * 3);
        let t = rng.uniform_vec(points, t_min as f64, 1.0 - t_min as f64);
        FlowNoise::from_host(gpu, &eps, &t)
    }

    /// Given noise (for deterministic checks).
    pub fn from_host(gpu: &Gpu, eps: &[f32], t: &[f32]) -> Result<FlowNoise> {
        if eps.len() != 3 * t.len() {
            return Err(Error::Shape(format!(
                "flow noise: {} noise values for {} flow times (need 3 per point)",
                eps.len(),
                t.len()
            )));
        }
        Ok(FlowNoise {
            eps: Tensor::from_slice(gpu, &[t.len(), 3], eps)?,
            t: Tensor::from_slice(gpu, &[t.len()], t)?,
        })
    }
}

/// One training step's outputs: `L_V` as a 1-element tensor (read it after submit) and its
/// gradient with respect to the tokens, for the encoder.
pub struct FlowLoss {
    pub loss: Tensor,
    pub dtokens: Tensor,
}

/// ODE integrators for sampling.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sampler {
    /// `x += dt v(x, t)`: one velocity per step.
    Euler,
    /// Heun's (trapezoidal predictor-corrector) method: two velocities per step, second order.
    Heun,
}

/// What to sample: `points` points, `steps` integration steps, noise from `seed`, the velocity
/// network run in `precision` (the f16 path needs the store's f16 copies synced first).
#[derive(Clone, Copy, Debug)]
pub struct SampleSpec {
    pub points: usize,
    pub steps: usize,
    pub sampler: Sampler,
    pub seed: u64,
    pub precision: Precision,
}

/// Host points `[N, 3]` as a tensor, refusing empty, ragged or non-finite input with a message
/// that names the first bad point.
pub fn points_tensor(gpu: &Gpu, points: &[f32]) -> Result<Tensor> {
    if points.is_empty() || !points.len().is_multiple_of(3) {
        return Err(Error::Invalid(format!(
            "surface decoder: points must be a non-empty list of xyz triples, got {} values",
            points.len()
        )));
    }
    if let Some(i) = points.iter().position(|v| !v.is_finite()) {
        return Err(Error::Invalid(format!(
            "surface decoder: point {} has a non-finite coordinate ({})",
            i / 3,
            points[i]
        )));
    }
    Tensor::from_slice(gpu, &[points.len() / 3, 3], points)
}

/// Integrates `dx/dt = velocity(x, t)` from `t = 0` to `t = 1` in `steps` equal steps, one
/// submission per step (so activations of a step are freed before the next). `velocity`
/// records its work on the recorder it is given and returns `v` of `x`'s shape.
pub fn integrate<F>(x0: &Tensor, steps: usize, sampler: Sampler, mut velocity: F) -> Result<Tensor>
where
    F: FnMut(&mut Recorder, &Tensor, f32) -> Result<Tensor>,
{
    if steps == 0 {
        return Err(Error::Invalid("sampling needs at least one integration step".into()));
    }
    let gpu = x0.gpu().clone();
    let dt = 1.0 / steps as f32;
    let mut x = x0.clone();
    for i in 0..steps {
        let t = i as f32 * dt;
        let mut rec = gpu.recorder()?;
        let v1 = velocity(&mut rec, &x, t)?;
        check_velocity(&x, &v1)?;
        let next = match sampler {
            Sampler::Euler => {
                let step = unary(&mut rec, &v1, Unary::Affine(dt, 0.0))?;
                binary(&mut rec, &x, &step, Binary::Add)?
            }
            Sampler::Heun => {
                let step = unary(&mut rec, &v1, Unary::Affine(dt, 0.0))?;
                let predicted = binary(&mut rec, &x, &step, Binary::Add)?;
                let v2 = velocity(&mut rec, &predicted, (i + 1) as f32 * dt)?;
                check_velocity(&x, &v2)?;
                let sum = binary(&mut rec, &v1, &v2, Binary::Add)?;
                unary_inplace(&mut rec, &sum, Unary::Affine(0.5 * dt, 0.0))?;
                binary(&mut rec, &x, &sum, Binary::Add)?
            }
        };
        rec.submit()?;
        x = next;
    }
    Ok(x)
}

fn unary_inplace(rec: &mut Recorder, x: &Tensor, f: Unary) -> Result<()> {
    velox_engine::ops::unary::unary_into(rec, x, x, f)
}

fn check_velocity(x: &Tensor, v: &Tensor) -> Result<()> {
    if v.shape() != x.shape() || v.dtype() != DType::F32 {
        return Err(Error::Shape(format!("sampler: velocity {v:?} does not match the points {x:?}")));
    }
    Ok(())
}

impl SurfaceDecoder {
    /// The decoder, its parameters under `prefix` (`.input`, `.time`, `.blocks.{i}`, `.final`,
    /// `.out`), reading `token_dim`-wide tokens.
    pub fn new(
        p: &mut Params,
        prefix: &str,
        cfg: &SurfaceConfig,
        token_dim: usize,
    ) -> Result<SurfaceDecoder> {
        check_config(cfg, token_dim)?;
        let gpu = p.gpu().clone();
        let (xyz, tau, time) = feature_widths(cfg);
        let (w, te) = (cfg.width, cfg.time_embed);
        let name = |s: &str| format!("{prefix}.{s}");
        // Glorot over the whole input linear, whose rows are split into two parameters.
        let a = (6.0 / (xyz + tau + w) as f64).sqrt();
        let glorot = Init::Uniform { lo: -a, hi: a };
        let input_w = p.param(&name("input.w"), &[xyz, w], glorot)?;
        let input = Linear::new(input_w, Some(p.param(&name("input.b"), &[w], Init::Zeros)?))?;
        let input_tau = (tau > 0)
            .then(|| Linear::new(p.param(&name("input_tau.w"), &[tau, w], glorot)?, None))
            .transpose()?;
        let time = TimeEmbedding {
            fourier: Fourier::log_spaced(&gpu, 1, cfg.time_freqs, cfg.time_max_octave, true)?,
            fc1: linear(p, &name("time.fc1"), time, te, true)?,
            fc2: linear(p, &name("time.fc2"), te, te, true)?,
        };
        let roles =
            |base: String, roles: &[&str]| roles.iter().map(|r| format!("{base}.{r}")).collect::<Vec<_>>();
        let mut blocks = Vec::with_capacity(cfg.blocks);
        for i in 0..cfg.blocks {
            let blk = |s: &str| name(&format!("blocks.{i}.{s}"));
            blocks.push(Block {
                attn: attention(p, &blk("attn"), w, token_dim, cfg.heads)?,
                mlp: mlp(p, &blk("mlp"), w, cfg.mlp_ratio * w, w)?,
                adaln: Modulation::new(p, &roles(blk("adaln"), &BLOCK_ROLES), te, w)?,
            });
        }
        let final_adaln = Modulation::new(p, &roles(name("final.adaln"), &FINAL_ROLES), te, w)?;
        let out_w = p.param(&name("out.w"), &[w, 3], Init::Zeros)?;
        let out = Linear::new(out_w, Some(p.param(&name("out.b"), &[3], Init::Zeros)?))?;
        Ok(SurfaceDecoder {
            cfg: cfg.clone(),
            token_dim,
            xyz_fourier: Fourier::log_spaced(&gpu, 3, cfg.xyz_freqs, cfg.xyz_max_octave, true)?,
            tau_fourier: (cfg.tau_freqs > 0)
                .then(|| Fourier::log_spaced(&gpu, 1, cfg.tau_freqs, cfg.tau_max_octave, false))
                .transpose()?,
            input,
            input_tau,
            time,
            blocks,
            final_adaln,
            out,
            norm: LayerNorm::new(cfg.width, None, LN_EPS)?,
        })
    }

    /// A decoder in a store of its own (for benchmarks and tests), initialised with `seed`.
    pub fn standalone(
        gpu: &Gpu,
        cfg: &SurfaceConfig,
        token_dim: usize,
        seed: u64,
    ) -> Result<(ParamStore, SurfaceDecoder)> {
        let (dec, store) = build(gpu, seed, |p| SurfaceDecoder::new(p, "surface", cfg, token_dim))?;
        Ok((store, dec))
    }

    /// Multiply-adds of one forward pass over `points` points and `tokens` tokens, times two
    /// (FLOPs): the matmuls and attention that grow with the points, plus each block's key and
    /// value projections of the tokens. The time embedding and modulation (one row when `t` is
    /// shared, as in sampling) are left out.
    pub fn forward_flops(cfg: &SurfaceConfig, token_dim: usize, points: usize, tokens: usize) -> u64 {
        let (xyz, _, _) = feature_widths(cfg);
        let (n, k, w) = (points as u64, tokens as u64, cfg.width as u64);
        let hidden = cfg.mlp_ratio as u64 * w;
        let per_block = n * (2 * w * w + 2 * w * hidden) + 2 * k * token_dim as u64 * w + 2 * n * k * w;
        2 * (n * xyz as u64 * w + cfg.blocks as u64 * per_block + n * w * 3)
    }

    fn check_inputs(
        &self,
        x_t: &Tensor,
        frames: &PointFrames,
        t: &Tensor,
        tokens: &Tensor,
    ) -> Result<(usize, usize)> {
        let n = match x_t.shape() {
            [n, 3] if *n > 0 && x_t.dtype() == DType::F32 => *n,
            _ => {
                return Err(Error::Shape(format!(
                    "surface decoder: points must be f32 [N, 3] with N > 0, got {x_t:?}"
                )))
            }
        };
        if t.dtype() != DType::F32 || (t.shape() != [n] && t.shape() != [1]) {
            return Err(Error::Shape(format!(
                "surface decoder: flow times must be f32 [{n}] (one per point) or [1] (shared), got {t:?}"
            )));
        }
        let groups = frames.taus.len();
        if groups == 0 || !n.is_multiple_of(groups) {
            return Err(Error::Shape(format!(
                "surface decoder: {n} points do not split into {groups} equal frame groups"
            )));
        }
        let mut k = 0;
        for &tau in &frames.taus {
            k = self.check_condition(tau, tokens)?;
        }
        Ok((n, k))
    }

    /// Checks the frame time and the tokens; returns the number of tokens.
    fn check_condition(&self, tau: f32, tokens: &Tensor) -> Result<usize> {
        if !tau.is_finite() {
            return Err(Error::Invalid(format!("surface decoder: frame time tau is {tau}")));
        }
        match tokens.shape() {
            [k, d] if *k > 0 && *d == self.token_dim && tokens.dtype() == DType::F32 => Ok(*k),
            _ => Err(Error::Shape(format!(
                "surface decoder: tokens must be f32 [k, {}] with k > 0, got {tokens:?}",
                self.token_dim
            ))),
        }
    }

    /// The velocity `v [N, 3]` at points `x_t [N, 3]` of frame time `tau`, flow times `t [N]`
    /// (or `[1]`, shared by every point), given the tokens `[k, token_dim]`.
    pub fn forward(
        &self,
        rec: &mut Recorder,
        x_t: &Tensor,
        tau: f32,
        t: &Tensor,
        tokens: &Tensor,
    ) -> Result<(Tensor, SurfaceCache)> {
        let frames = PointFrames::single(
            x_t.gpu(),
            tau,
            x_t.shape()[0],
            tokens.shape().first().copied().unwrap_or(0),
        )?;
        self.forward_frames(rec, x_t, &frames, t, tokens)
    }

    /// [`SurfaceDecoder::forward`] of a batch: the points' frame times and tokens as `frames`
    /// says (the tokens of every sample of the batch, one after another).
    pub fn forward_frames(
        &self,
        rec: &mut Recorder,
        x_t: &Tensor,
        frames: &PointFrames,
        t: &Tensor,
        tokens: &Tensor,
    ) -> Result<(Tensor, SurfaceCache)> {
        let (n, k) = self.check_inputs(x_t, frames, t, tokens)?;
        let groups = frames.taus.len();
        let gpu = x_t.gpu().clone();
        let w = self.cfg.width;
        let nt = t.numel();
        let (b, tt) = if nt == n { (n, 1) } else { (1, n) };

        // Time embedding e [nt, time_embed] and the modulation chunks [nt, width].
        let (e, time) = self.time.forward(rec, t)?;
        let mut e_cache = None;

        // Input features.
        let (fx, _) = self.xyz_fourier.forward(rec, x_t)?;
        let (h, input) = self.input.forward(rec, &fx)?;
        // Each frame group's row of Fourier(tau) through its linear, added to its points.
        let input_tau = match (&self.tau_fourier, &self.input_tau) {
            (Some(f), Some(l)) => {
                let tau_t = Tensor::from_slice(&gpu, &[groups, 1], &frames.taus)?;
                let (ftau, _) = f.forward(rec, &tau_t)?;
                let (rows, c) = l.forward(rec, &ftau)?;
                let grouped = h.reshape(&[groups, n / groups, w])?;
                binary_into(rec, &grouped, &rows.reshape(&[groups, 1, w])?, &grouped, Binary::Add)?;
                Some(c)
            }
            _ => None,
        };

        let seg = frames.segments.clone();
        let mut h = h.reshape(&[b, tt, w])?;
        let mut blocks = Vec::with_capacity(self.blocks.len());
        for blk in &self.blocks {
            let m = blk.adaln.forward(rec, &e, &mut e_cache)?;
            let (n1, ln1) = self.norm.forward(rec, &h)?;
            let (m1, mod1) = Modulate.forward(rec, &n1, &m[0], &m[1])?;
            let (a, attn) = blk.attn.forward(rec, &m1.reshape(&[n, w])?, Some(tokens), &seg)?;
            let (h1, res1) = GatedResidual.forward(rec, &h, &m[2], &a.reshape(&[b, tt, w])?)?;
            let (n2, ln2) = self.norm.forward(rec, &h1)?;
            let (m2, mod2) = Modulate.forward(rec, &n2, &m[3], &m[4])?;
            let (f, mlp) = blk.mlp.forward(rec, &m2)?;
            let (h2, res2) = GatedResidual.forward(rec, &h1, &m[5], &f)?;
            blocks.push(BlockCache { ln1, mod1, attn, res1, ln2, mod2, mlp, res2 });
            h = h2;
        }
        let m = self.final_adaln.forward(rec, &e, &mut e_cache)?;
        let (nf, ln_final) = self.norm.forward(rec, &h)?;
        let (mf, mod_final) = Modulate.forward(rec, &nf, &m[0], &m[1])?;
        let (v, out) = self.out.forward(rec, &mf.reshape(&[n, w])?)?;
        let cache = SurfaceCache {
            n,
            groups,
            b,
            tt,
            k,
            seg,
            time,
            e: e_cache.expect("the final layer always has a modulation"),
            input,
            input_tau,
            blocks,
            ln_final,
            mod_final,
            out,
        };
        Ok((v, cache))
    }

    /// Adds every parameter gradient for `dv [N, 3]`; returns the tokens' gradient `[k, token_dim]`.
    pub fn backward(&self, rec: &mut Recorder, cache: &SurfaceCache, dv: &Tensor) -> Result<Tensor> {
        let dtokens = Tensor::empty(dv.gpu(), &[cache.k, self.token_dim], DType::F32)?;
        self.backward_into(rec, cache, dv, &dtokens, false)?;
        Ok(dtokens)
    }

    /// [`SurfaceDecoder::backward`] with the tokens' gradient written into `dtokens`, or added
    /// to what it holds (`accumulate`: the tokens feed other decoders too).
    pub fn backward_into(
        &self,
        rec: &mut Recorder,
        cache: &SurfaceCache,
        dv: &Tensor,
        dtokens: &Tensor,
        accumulate: bool,
    ) -> Result<()> {
        let (n, b, tt, w) = (cache.n, cache.b, cache.tt, self.cfg.width);
        if dv.shape() != [n, 3] || dv.dtype() != DType::F32 {
            return Err(Error::Shape(format!(
                "surface decoder backward: dv must be f32 [{n}, 3], got {dv:?}"
            )));
        }
        let gpu = dv.gpu().clone();
        let nt = b; // the modulation rows: one per point, or one shared by all
        let te = self.cfg.time_embed;
        // The time embedding's gradient, summed over every modulation that reads it.
        let de = Tensor::empty(&gpu, &[nt, te], DType::F32)?;
        let mut de_started = false;

        let dmf = self.out.backward(rec, &cache.out, dv)?;
        let g = Modulate.backward(rec, &cache.mod_final, &dmf.reshape(&[b, tt, w])?)?;
        self.final_adaln.backward(rec, &cache.e, &[&g.dshift, &g.dscale], &de, &mut de_started)?;
        let mut dh = self.norm.backward(rec, &cache.ln_final, &g.dx)?;

        if dtokens.shape() != [cache.k, self.token_dim] || dtokens.dtype() != DType::F32 {
            return Err(Error::Shape(format!(
                "surface decoder backward: the tokens' gradient must be f32 [{}, {}], got {dtokens:?}",
                cache.k, self.token_dim
            )));
        }
        let mut dtokens_started = accumulate;
        for (blk, c) in self.blocks.iter().zip(&cache.blocks).rev() {
            // MLP branch: h2 = h1 + gate_m * mlp(mod(LN(h1))).
            let r2 = GatedResidual.backward(rec, &c.res2, &dh)?;
            let dm2 = blk.mlp.backward(rec, &c.mlp, &r2.dy)?;
            let g2 = Modulate.backward(rec, &c.mod2, &dm2)?;
            let dh1 = self.norm.backward_plus(rec, &c.ln2, &g2.dx, Some(&r2.dres))?;
            // Attention branch: h1 = h + gate_a * attn(mod(LN(h)), tokens).
            let r = GatedResidual.backward(rec, &c.res1, &dh1)?;
            let dy = r.dy.reshape(&[n, w])?;
            let dm1 = blk.attn.backward_into(rec, &c.attn, &dy, &cache.seg, dtokens, dtokens_started)?;
            dtokens_started = true;
            let g = Modulate.backward(rec, &c.mod1, &dm1.reshape(&[b, tt, w])?)?;
            // The block's six modulations, in BLOCK_ROLES order.
            let dm = [&g.dshift, &g.dscale, &r.dgate, &g2.dshift, &g2.dscale, &r2.dgate];
            blk.adaln.backward(rec, &cache.e, &dm, &de, &mut de_started)?;
            dh = self.norm.backward_plus(rec, &c.ln1, &g.dx, Some(&r.dres))?;
        }
        if !dtokens_started {
            fill(rec, dtokens, 0.0)?;
        }

        // Input linear: the point rows see every point's gradient, the tau rows their sum.
        let dh = dh.reshape(&[n, w])?;
        self.input.param_grads(rec, &cache.input, &dh)?;
        if let (Some(l), Some(c)) = (&self.input_tau, &cache.input_tau) {
            let g = cache.groups;
            let sum = reduce(rec, &dh.reshape(&[g, n / g, w])?, 1, Reduce::Sum)?;
            l.param_grads(rec, c, &sum)?;
        }

        // Time embedding: e = silu(fc2(silu(fc1(Fourier(t))))).
        self.time.backward(rec, &cache.time, &de)
    }

    /// `x_t = t x + (1 - t) eps` and the target velocity `u = x - eps`.
    pub fn flow_pair(rec: &mut Recorder, x: &Tensor, noise: &FlowNoise) -> Result<(Tensor, Tensor)> {
        if x.shape() != noise.eps.shape() {
            return Err(Error::Shape(format!(
                "rectified flow: points {x:?} and noise {:?} differ",
                noise.eps.shape()
            )));
        }
        // x_t = t x + (1 - t) eps = eps + t u.
        let t = noise.t.reshape(&[noise.t.numel(), 1])?;
        let u = binary(rec, x, &noise.eps, Binary::Sub)?;
        let x_t = binary(rec, &u, &t, Binary::Mul)?;
        binary_into(rec, &x_t, &noise.eps, &x_t, Binary::Add)?;
        Ok((x_t, u))
    }

    /// The forward pass of `weight L_V` under given noise: `(loss [1], dL/dv, cache)`. Adds no
    /// gradients (finite-difference checks use it alone).
    pub fn flow_loss(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        tau: f32,
        tokens: &Tensor,
        noise: &FlowNoise,
        weight: f32,
    ) -> Result<(Tensor, Tensor, SurfaceCache)> {
        let frames =
            PointFrames::single(x.gpu(), tau, x.shape()[0], tokens.shape().first().copied().unwrap_or(0))?;
        self.flow_loss_frames(rec, x, &frames, tokens, noise, weight)
    }

    /// [`SurfaceDecoder::flow_loss`] of a batch of points (see [`PointFrames`]): `L_V` is the
    /// mean over all of them.
    pub fn flow_loss_frames(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        frames: &PointFrames,
        tokens: &Tensor,
        noise: &FlowNoise,
        weight: f32,
    ) -> Result<(Tensor, Tensor, SurfaceCache)> {
        let (x_t, u) = SurfaceDecoder::flow_pair(rec, x, noise)?;
        let (v, cache) = self.forward_frames(rec, &x_t, frames, &noise.t, tokens)?;
        let (loss, dv) = Loss::mse().weighted(weight).forward_backward(rec, &v, &u)?;
        Ok((loss, dv, cache))
    }

    /// One training step of `weight L_V` under given noise: forward, loss and backward
    /// (parameter gradients added into the store).
    pub fn loss_step_with(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        tau: f32,
        tokens: &Tensor,
        noise: &FlowNoise,
        weight: f32,
    ) -> Result<FlowLoss> {
        let (loss, dv, cache) = self.flow_loss(rec, x, tau, tokens, noise, weight)?;
        let dtokens = self.backward(rec, &cache, &dv)?;
        Ok(FlowLoss { loss, dtokens })
    }

    /// One training step of `weight L_V` on points `x [N, 3]` of frame time `tau`: draws `eps`
    /// and `t` from `rng` on the host, then as [`SurfaceDecoder::loss_step_with`].
    pub fn loss_step(
        &self,
        rec: &mut Recorder,
        x: &Tensor,
        tau: f32,
        tokens: &Tensor,
        rng: &mut Rng,
        weight: f32,
    ) -> Result<FlowLoss> {
        let n = match x.shape() {
            [n, 3] if *n > 0 => *n,
            _ => {
                return Err(Error::Shape(format!("surface decoder: points must be [N, 3], N > 0, got {x:?}")))
            }
        };
        let noise = FlowNoise::draw(x.gpu(), n, self.cfg.t_min, rng)?;
        self.loss_step_with(rec, x, tau, tokens, &noise, weight)
    }

    /// Points per sampling chunk on `gpu`: the MLP's hidden activation of a chunk stays within
    /// [`SAMPLE_CHUNK_BYTES`], and chunks start at offsets every device can bind.
    pub fn sample_chunk(&self, gpu: &Gpu) -> usize {
        let (lo, hi) = SAMPLE_CHUNK_BYTES;
        let bytes = (gpu.caps().max_storage_buffer_range / 4).clamp(lo, hi) as usize;
        let per_point = 4 * self.cfg.mlp_ratio.max(1) * self.cfg.width;
        (bytes / per_point).max(64) / 64 * 64
    }

    /// Samples `spec.points` surface points at frame time `tau` from `x_0 ~ N(0, I)` (seeded)
    /// by integrating the velocity from `t = 0` to `1`: `[points, 3]`.
    pub fn sample(&self, tokens: &Tensor, tau: f32, spec: &SampleSpec) -> Result<Tensor> {
        self.sample_in_chunks(tokens, tau, spec, self.sample_chunk(tokens.gpu()))
    }

    /// [`SurfaceDecoder::sample`] integrating `chunk` points at a time (a positive multiple of
    /// 64); point `i` starts from the same noise whatever the chunk.
    pub fn sample_in_chunks(
        &self,
        tokens: &Tensor,
        tau: f32,
        spec: &SampleSpec,
        chunk: usize,
    ) -> Result<Tensor> {
        if spec.points == 0 {
            return Err(Error::Invalid("sampling needs at least one point".into()));
        }
        if spec.steps == 0 {
            return Err(Error::Invalid("sampling needs at least one integration step".into()));
        }
        if chunk == 0 || !chunk.is_multiple_of(64) {
            return Err(Error::Invalid(format!("sampling chunk {chunk} is not a positive multiple of 64")));
        }
        self.check_condition(tau, tokens)?;
        let gpu = tokens.gpu().clone();
        let noise = Rng::new(spec.seed).normal_vec(spec.points * 3);
        let out = Tensor::empty(&gpu, &[spec.points, 3], DType::F32)?;
        for start in (0..spec.points).step_by(chunk) {
            let len = chunk.min(spec.points - start);
            let x0 = Tensor::from_slice(&gpu, &[len, 3], &noise[3 * start..3 * (start + len)])?;
            let x1 = integrate(&x0, spec.steps, spec.sampler, |rec, x, t| {
                rec.set_precision(spec.precision);
                let tt = Tensor::from_slice(&gpu, &[1], &[t])?;
                Ok(self.forward(rec, x, tau, &tt, tokens)?.0)
            })?;
            let mut rec = gpu.recorder()?;
            rec.copy(&x1, &out.view(3 * start, &[len, 3])?)?;
            rec.submit()?;
        }
        Ok(out)
    }
}
