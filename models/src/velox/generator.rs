//! The generator (docs/models.md, Generation; paper Sec. 3 and supplement): a DiT that turns a
//! video (or one image) into the dynamic tokens of the object it shows, by rectified flow on
//! the tokens normalised by the dataset's statistics.
//!
//! The velocity network, for `B` scenes of `k` tokens each (patch size 1: a token is a
//! transformer token):
//! ```text
//! h = x_t W_in + b_in + P                       P [k, width]: learned positions, zero at first
//! e = silu(MLP(Fourier(t)))                     time embedding [B, width]
//! m_r = e W_r + b_r, r = 0..6                   one modulation for every block (adaLN-single)
//! each block i, with m_ir = m_r + T_ir (a learned [6, width] table per block):
//!     h += m_i2 * SelfAttn(RMSNorm(h) * (1 + m_i1) + m_i0)          adaLN-Zero gates
//!     h += CrossAttn(RMSNorm(h), c)                                 output projection zero at first
//!     h += m_i5 * GeluMlp(RMSNorm(h) * (1 + m_i4) + m_i3)
//! v = (RMSNorm(h) * (1 + f_1) + f_0) W_out + b_out                  f_r = e F_r + g_r; W_out zero
//! c = C W_c + b_c                                 the condition tokens in the model's width
//! C = [DINOv2(frame) ++ RGB patch W_rgb + b_rgb ++ Fourier(frame time)] per frame and patch
//! ```
//! Every gate, the cross-attention's output projection and `W_out` start at zero, so the
//! untrained network outputs 0 and each block starts as the identity.
//!
//! One modulation shared by the blocks plus a table per block (PixArt-alpha's adaLN-single),
//! and one projection of the condition shared by the blocks' keys and values, is what brings
//! the paper's sizes (28 blocks of 1152, 2065-wide condition) to its 623 M parameters: a
//! modulation linear per block, as in DiT, adds 223 M, and keys and values read from the
//! 2065-wide condition in every block add 59 M.
//!
//! Training (rectified flow, as the surface decoder): `x_t = t x + (1 - t) eps`, target
//! `u = x - eps`, `t` uniform in `[t_min, 1 - t_min]` per scene; with probability
//! `cond_dropout` a scene sees the null condition (its condition tokens all zero), which
//! classifier-free guidance needs. Sampling integrates from `t = 0` (noise) to 1 with Euler or
//! Heun steps and guidance `v = v_null + s (v_cond - v_null)`; the condition's keys and values
//! are computed once per generation, not once per step.
//!
//! Tests: `tests/models/generator.rs` (the step per part against finite differences, learning),
//! `tests/models/slips.rs` (one guided step is the guided combination; condition dropout; the flow
//! noise).

use velox_engine::ops::adamw::AdamWConfig;
use velox_engine::ops::attention::Segments;
use velox_engine::ops::binary::{binary, binary_into, Binary};
use velox_engine::ops::columns::{columns, copy_columns};
use velox_engine::ops::reduce::{reduce, Reduce};
use velox_engine::ops::unary::{unary, Unary};
use velox_engine::rng::Rng;
use velox_engine::{DType, Error, Gpu, Precision, Recorder, Result, Tensor};

use crate::config::GeneratorConfig;
use crate::layers::adaln::{GatedResidualCache, ModulateCache};
use crate::layers::attention::MultiHeadAttentionCache;
use crate::layers::feedforward::GeluMlpCache;
use crate::layers::linear::LinearCache;
use crate::layers::norm::RmsNormCache;
use crate::layers::{
    Fourier, GatedResidual, GeluMlp, Linear, Loss, Modulate, MultiHeadAttention, Param, RmsNorm,
};
use crate::params::{build, declare, Init, ParamBuilder, ParamStore, Params};
use crate::train::{Ahead, Losses, PassSeconds, PassTimer};
use crate::velox::blocks::{mlp, norm, TimeEmbedding, TimeEmbeddingCache};
use crate::velox::dinov2::{PATCH, PATCH_VALUES};
use crate::velox::surface::{integrate, Sampler};

/// The `model` a checkpoint of the generator names.
pub const MODEL_KIND: &str = "velox generator";

/// The modulation roles of a block, then of the final layer.
const BLOCK_ROLES: [&str; 6] =
    ["shift_attn", "scale_attn", "gate_attn", "shift_mlp", "scale_mlp", "gate_mlp"];
const FINAL_ROLES: [&str; 2] = ["shift", "scale"];

/// A scene's condition: the RGB patches of its frames and, with DINOv2, their features.
pub struct Condition {
    /// `[frames * patches, PATCH_VALUES]`: per frame its patches in raster order (as
    /// [`crate::velox::dinov2::Dinov2::patch_rows`] lays them out, without the class rows),
    /// pixels normalised as DINOv2 reads them.
    pub patches: Tensor,
    /// `[frames * patches, dino_width]`: the DINOv2 patch features, when the generator reads
    /// them.
    pub dino: Option<Tensor>,
}

/// What the generator trains on from one scene.
pub struct GenSample {
    /// `[k, token_dim]`: the scene's tokens, normalised by the dataset's statistics.
    pub tokens: Tensor,
    pub condition: Condition,
}

struct Block {
    norm1: RmsNorm,
    attn: MultiHeadAttention,
    norm2: RmsNorm,
    cross: MultiHeadAttention,
    norm3: RmsNorm,
    mlp: GeluMlp,
    /// `BLOCK_ROLES`, each `[width]`: the block's offsets of the shared modulation.
    table: Vec<Param>,
}

struct BlockCache {
    n1: RmsNormCache,
    mod1: ModulateCache,
    attn: MultiHeadAttentionCache,
    res1: GatedResidualCache,
    n2: RmsNormCache,
    cross: Option<MultiHeadAttentionCache>,
    n3: RmsNormCache,
    mod3: ModulateCache,
    mlp: GeluMlpCache,
    res3: GatedResidualCache,
}

/// What the backward pass needs from the forward.
pub struct GenCache {
    b: usize,
    self_seg: Segments,
    cross_seg: Segments,
    input: LinearCache,
    time: TimeEmbeddingCache,
    e: LinearCache,
    blocks: Vec<BlockCache>,
    final_norm: RmsNormCache,
    mod_final: ModulateCache,
    out: LinearCache,
    cond: Option<CondCache>,
}

struct CondCache {
    rgb: LinearCache,
    embed: LinearCache,
    /// `[rows, 1]`: 0 for the rows of scenes that saw the null condition, else 1.
    keep: Tensor,
}

/// The condition as the blocks read it: computed in this pass (training), or keys and values
/// computed once (sampling).
enum Context<'a> {
    Embedded(&'a Tensor),
    Cached(&'a [(Tensor, Tensor)]),
}

/// What to generate: integration steps and sampler, guidance scale, the noise's seed and the
/// precision of the velocity network.
#[derive(Clone, Copy, Debug)]
pub struct GenerateSpec {
    pub steps: usize,
    pub sampler: Sampler,
    /// `v = v_null + guidance (v_cond - v_null)`; 1 runs the conditional network alone.
    pub guidance: f32,
    pub seed: u64,
    pub precision: Precision,
}

/// The generator; see the module docs.
pub struct Generator {
    pub cfg: GeneratorConfig,
    pub store: ParamStore,
    net: Net,
    pub adamw: AdamWConfig,
    pass_seconds: PassSeconds,
}

/// The generator's layers, over its store's parameters.
struct Net {
    input: Linear,
    positions: Param,
    time: TimeEmbedding,
    adaln: Vec<Linear>,
    final_adaln: Vec<Linear>,
    blocks: Vec<Block>,
    final_norm: RmsNorm,
    out: Linear,
    rgb: Linear,
    cond_embed: Linear,
    /// `[frames * patches, 1 + 2 frame_freqs]`: Fourier(frame time) of every condition row of
    /// a scene.
    frame_embed: Tensor,
}

impl Net {
    fn new(p: &mut Params, cfg: &GeneratorConfig) -> Result<Net> {
        let gpu = p.gpu().clone();
        let gpu = &gpu;
        let (w, d) = (cfg.width, cfg.token_dim);
        let time = 1 + 2 * cfg.time_freqs;
        let lin = |p: &mut Params, name: &str, i: usize, o: usize, init: Init| -> Result<Linear> {
            let w = p.param(&format!("{name}.w"), &[i, o], init)?;
            Linear::new(w, Some(p.param(&format!("{name}.b"), &[o], Init::Zeros)?))
        };
        let input = lin(p, "input", d, w, Init::Xavier)?;
        let positions = p.param("positions", &[cfg.tokens, w], Init::Zeros)?;
        let time = TimeEmbedding {
            fourier: Fourier::log_spaced(gpu, 1, cfg.time_freqs, cfg.time_max_octave, true)?,
            fc1: lin(p, "time.fc1", time, w, Init::Xavier)?,
            fc2: lin(p, "time.fc2", w, w, Init::Xavier)?,
        };
        let adaln = BLOCK_ROLES
            .iter()
            .map(|r| lin(p, &format!("adaln.{r}"), w, w, Init::Zeros))
            .collect::<Result<_>>()?;
        let final_adaln = FINAL_ROLES
            .iter()
            .map(|r| lin(p, &format!("final.adaln.{r}"), w, w, Init::Zeros))
            .collect::<Result<_>>()?;
        let rgb = lin(p, "rgb", PATCH_VALUES, cfg.rgb_width, Init::Xavier)?;
        let cond_embed = lin(p, "cond", cfg.cond_width(), w, Init::Xavier)?;
        // The cross-attention's output starts at zero: a block starts out ignoring the condition.
        let attention = |p: &mut Params, name: &str, o: Init| -> Result<MultiHeadAttention> {
            let mut l =
                |m: &str, init: Init| Linear::new(p.param(&format!("{name}.{m}.w"), &[w, w], init)?, None);
            let (q, k, v, o) =
                (l("q", Init::Xavier)?, l("k", Init::Xavier)?, l("v", Init::Xavier)?, l("o", o)?);
            MultiHeadAttention::new(q, k, v, o, cfg.heads)?
                .with_stacks(p, ["q", "k", "v"].map(|m| format!("{name}.{m}.w")))
        };
        let mut blocks = Vec::with_capacity(cfg.blocks);
        for i in 0..cfg.blocks {
            let n = |s: &str| format!("blocks.{i}.{s}");
            let [norm1, norm2, norm3] = [n("norm1"), n("norm2"), n("norm3")];
            let (norm1, norm2, norm3) = (norm(p, &norm1, w)?, norm(p, &norm2, w)?, norm(p, &norm3, w)?);
            let attn = attention(p, &n("attn"), Init::Xavier)?;
            let cross = attention(p, &n("cross"), Init::Zeros)?;
            let mlp = mlp(p, &n("mlp"), w, cfg.mlp_ratio * w, w)?;
            let table = BLOCK_ROLES
                .iter()
                .map(|r| p.param(&n(&format!("table.{r}")), &[w], Init::Zeros))
                .collect::<Result<_>>()?;
            blocks.push(Block { norm1, attn, norm2, cross, norm3, mlp, table });
        }
        let final_norm = norm(p, "final.norm", w)?;
        let out = lin(p, "out", w, d, Init::Zeros)?;
        // Fourier(frame time) of every condition row: frame f of F at f / (F - 1).
        let side = cfg.image_size / PATCH;
        let frames = cfg.task.frames();
        let times: Vec<f32> = (0..frames)
            .flat_map(|f| std::iter::repeat_n(f as f32 / (frames.max(2) - 1) as f32, side * side))
            .collect();
        let frame_fourier = Fourier::octaves(gpu, 1, cfg.frame_freqs, true)?;
        let mut rec = gpu.recorder()?;
        let (frame_embed, _) =
            frame_fourier.forward(&mut rec, &Tensor::from_slice(gpu, &[times.len(), 1], &times)?)?;
        rec.submit()?;
        Ok(Net {
            input,
            positions,
            time,
            adaln,
            final_adaln,
            blocks,
            final_norm,
            out,
            rgb,
            cond_embed,
            frame_embed,
        })
    }
}

impl Generator {
    /// A freshly initialised generator (parameters from `seed`).
    pub fn new(gpu: &Gpu, cfg: &GeneratorConfig, seed: u64) -> Result<Generator> {
        cfg.validate()?;
        let (net, store) = build(gpu, seed, |p| Net::new(p, cfg))?;
        Ok(Generator {
            cfg: cfg.clone(),
            store,
            net,
            adamw: AdamWConfig::default(),
            pass_seconds: PassSeconds::default(),
        })
    }

    /// The parameters a config declares, without allocating them.
    pub fn declare(gpu: &Gpu, cfg: &GeneratorConfig) -> Result<ParamBuilder> {
        cfg.validate()?;
        declare(gpu, |p| Net::new(p, cfg))
    }

    /// Condition rows of one scene.
    pub fn cond_rows(&self) -> usize {
        self.cfg.cond_tokens()
    }

    fn check_condition(&self, c: &Condition) -> Result<()> {
        let rows = self.cond_rows();
        if c.patches.shape() != [rows, PATCH_VALUES] || c.patches.dtype() != DType::F32 {
            return Err(Error::Shape(format!(
                "generator: condition patches must be f32 [{rows}, {PATCH_VALUES}] ({} frames of {} pixels), got {:?}",
                self.cfg.task.frames(),
                self.cfg.image_size,
                c.patches
            )));
        }
        match (&c.dino, self.cfg.dino_width) {
            (None, 0) => Ok(()),
            (Some(d), w) if w > 0 && d.shape() == [rows, w] && d.dtype() == DType::F32 => Ok(()),
            (None, w) => Err(Error::Invalid(format!(
                "generator: it was trained on {w}-wide DINOv2 features; give the same DINOv2 weights"
            ))),
            (Some(d), 0) => Err(Error::Invalid(format!(
                "generator: it was trained without DINOv2, but DINOv2 features {d:?} were given"
            ))),
            (Some(d), w) => {
                Err(Error::Shape(format!("generator: DINOv2 features must be [{rows}, {w}], got {d:?}")))
            }
        }
    }

    /// The condition tokens `C [B * rows, cond_width]` of `conditions`, the RGB embedding's
    /// cache, and their projection `c = C W_c + b_c`. `keep[s]` false gives scene `s` the null
    /// condition (its rows of `C` zero).
    fn embed_condition(
        &self,
        rec: &mut Recorder,
        conditions: &[&Condition],
        keep: &[bool],
    ) -> Result<(Tensor, CondCache)> {
        for c in conditions {
            self.check_condition(c)?;
        }
        let gpu = rec.gpu().clone();
        let (rows, b) = (self.cond_rows(), conditions.len());
        let n = rows * b;
        let (dw, rw, fw) = (self.cfg.dino_width, self.cfg.rgb_width, self.net.frame_embed.shape()[1]);
        let stack = |rec: &mut Recorder, parts: &[&Tensor], width: usize| -> Result<Tensor> {
            let all = Tensor::empty(&gpu, &[n, width], DType::F32)?;
            for (s, t) in parts.iter().enumerate() {
                rec.copy_rows(t, 0, &all, s * rows, rows)?;
            }
            Ok(all)
        };
        let patches = stack(rec, &conditions.iter().map(|c| &c.patches).collect::<Vec<_>>(), PATCH_VALUES)?;
        let (rgb, rgb_cache) = self.net.rgb.forward(rec, &patches)?;
        let big = Tensor::empty(&gpu, &[n, self.cfg.cond_width()], DType::F32)?;
        if dw > 0 {
            let dino: Vec<&Tensor> = conditions.iter().map(|c| c.dino.as_ref().expect("checked")).collect();
            let dino = stack(rec, &dino, dw)?;
            copy_columns(rec, &dino, 0, &big, 0, dw, 1.0)?;
        }
        copy_columns(rec, &rgb, 0, &big, dw, rw, 1.0)?;
        let frames = stack(rec, &vec![&self.net.frame_embed; b], fw)?;
        copy_columns(rec, &frames, 0, &big, dw + rw, fw, 1.0)?;
        let mask: Vec<f32> = keep.iter().flat_map(|&k| std::iter::repeat_n(k as u8 as f32, rows)).collect();
        let mask_t = Tensor::from_slice(&gpu, &[n, 1], &mask)?;
        if keep.contains(&false) {
            binary_into(rec, &big, &mask_t, &big, Binary::Mul)?;
        }
        let (c, embed) = self.net.cond_embed.forward(rec, &big)?;
        Ok((c, CondCache { rgb: rgb_cache, embed, keep: mask_t }))
    }

    fn check_tokens(&self, x: &Tensor) -> Result<usize> {
        let (k, d) = (self.cfg.tokens, self.cfg.token_dim);
        match x.shape() {
            [n, dd] if *dd == d && *n > 0 && n.is_multiple_of(k) && x.dtype() == DType::F32 => Ok(n / k),
            _ => Err(Error::Shape(format!(
                "generator: tokens must be f32 [B x {k}, {d}] (the autoencoder's token count and width), got {x:?}"
            ))),
        }
    }

    /// The velocity `[B k, token_dim]` at `x_t` (`B` scenes' tokens one after another) and flow
    /// times `t [B]`, reading the condition as `context` gives it with `cond_lens[s]` rows for
    /// scene `s`.
    fn forward(
        &self,
        rec: &mut Recorder,
        x_t: &Tensor,
        t: &Tensor,
        context: Context,
        cond_lens: &[usize],
    ) -> Result<(Tensor, GenCache)> {
        let b = self.check_tokens(x_t)?;
        let (k, w) = (self.cfg.tokens, self.cfg.width);
        if t.shape() != [b] || cond_lens.len() != b {
            return Err(Error::Shape(format!(
                "generator: {b} scenes need {b} flow times and condition lengths, got {t:?} and {}",
                cond_lens.len()
            )));
        }
        let gpu = x_t.gpu().clone();
        let self_seg = Segments::from_lengths(&gpu, &vec![k; b], &vec![k; b])?;
        let cross_seg = Segments::from_lengths(&gpu, &vec![k; b], cond_lens)?;

        let (e, time) = self.net.time.forward(rec, t)?;
        let mut e_cache = None;
        let mut modulation = |rec: &mut Recorder, l: &Linear| -> Result<Tensor> {
            let (m, c) = l.forward(rec, &e)?;
            e_cache.get_or_insert(c);
            Ok(m)
        };
        let shared: Vec<Tensor> = self.net.adaln.iter().map(|l| modulation(rec, l)).collect::<Result<_>>()?;
        let fin: Vec<Tensor> =
            self.net.final_adaln.iter().map(|l| modulation(rec, l)).collect::<Result<_>>()?;

        let (h, input) = self.net.input.forward(rec, x_t)?;
        let mut h = h.reshape(&[b, k, w])?;
        binary_into(rec, &h, &self.net.positions.value, &h, Binary::Add)?;

        let mut blocks = Vec::with_capacity(self.net.blocks.len());
        for (i, blk) in self.net.blocks.iter().enumerate() {
            let m: Vec<Tensor> = shared
                .iter()
                .zip(&blk.table)
                .map(|(s, tab)| binary(rec, s, &tab.value, Binary::Add))
                .collect::<Result<_>>()?;
            let (n1, c_n1) = blk.norm1.forward(rec, &h)?;
            let (m1, mod1) = Modulate.forward(rec, &n1, &m[0], &m[1])?;
            let (a, attn) = blk.attn.forward(rec, &m1.reshape(&[b * k, w])?, None, &self_seg)?;
            let (h1, res1) = GatedResidual.forward(rec, &h, &m[2], &a.reshape(&[b, k, w])?)?;
            let (n2, c_n2) = blk.norm2.forward(rec, &h1)?;
            let n2 = n2.reshape(&[b * k, w])?;
            let (c, cross) = match &context {
                Context::Embedded(ctx) => {
                    let (c, cache) = blk.cross.forward(rec, &n2, Some(ctx), &cross_seg)?;
                    (c, Some(cache))
                }
                Context::Cached(kv) => {
                    (blk.cross.forward_kv(rec, &n2, &kv[i].0, &kv[i].1, &cross_seg)?, None)
                }
            };
            let h2 = binary(rec, &h1, &c.reshape(&[b, k, w])?, Binary::Add)?;
            let (n3, c_n3) = blk.norm3.forward(rec, &h2)?;
            let (m3, mod3) = Modulate.forward(rec, &n3, &m[3], &m[4])?;
            let (f, mlp) = blk.mlp.forward(rec, &m3)?;
            let (h3, res3) = GatedResidual.forward(rec, &h2, &m[5], &f)?;
            blocks.push(BlockCache {
                n1: c_n1,
                mod1,
                attn,
                res1,
                n2: c_n2,
                cross,
                n3: c_n3,
                mod3,
                mlp,
                res3,
            });
            h = h3;
        }
        let (nf, final_norm) = self.net.final_norm.forward(rec, &h)?;
        let (mf, mod_final) = Modulate.forward(rec, &nf, &fin[0], &fin[1])?;
        let (v, out) = self.net.out.forward(rec, &mf.reshape(&[b * k, w])?)?;
        let cache = GenCache {
            b,
            self_seg,
            cross_seg,
            input,
            time,
            e: e_cache.expect("the blocks always read a modulation"),
            blocks,
            final_norm,
            mod_final,
            out,
            cond: None,
        };
        Ok((v, cache))
    }

    /// Adds every parameter's gradient for `dv [B k, token_dim]`.
    fn backward(&self, rec: &mut Recorder, cache: &GenCache, dv: &Tensor) -> Result<()> {
        let (b, k, w) = (cache.b, self.cfg.tokens, self.cfg.width);
        let gpu = dv.gpu().clone();
        // The shared modulations' gradients, summed over the blocks, then one backward each.
        let dshared: Vec<Tensor> = (0..BLOCK_ROLES.len())
            .map(|_| Tensor::empty(&gpu, &[b, w], DType::F32))
            .collect::<Result<_>>()?;
        let mut started = [false; 6];
        let mut add_role = |rec: &mut Recorder, blk: &Block, r: usize, dm: &Tensor| -> Result<()> {
            let dt = reduce(rec, dm, 0, Reduce::Sum)?;
            binary_into(rec, &blk.table[r].grad, &dt, &blk.table[r].grad, Binary::Add)?;
            if started[r] {
                binary_into(rec, &dshared[r], dm, &dshared[r], Binary::Add)
            } else {
                started[r] = true;
                rec.copy(dm, &dshared[r])
            }
        };
        let dctx = match &cache.cond {
            Some(_) => Some(Tensor::empty(&gpu, &[cache.cross_seg_rows(), w], DType::F32)?),
            None => None,
        };
        let mut dctx_started = false;

        let dmf = self.net.out.backward(rec, &cache.out, dv)?;
        let gf = Modulate.backward(rec, &cache.mod_final, &dmf.reshape(&[b, k, w])?)?;
        let mut dh = self.net.final_norm.backward(rec, &cache.final_norm, &gf.dx)?;
        for (blk, c) in self.net.blocks.iter().zip(&cache.blocks).rev() {
            // MLP branch.
            let r3 = GatedResidual.backward(rec, &c.res3, &dh)?;
            add_role(rec, blk, 5, &r3.dgate)?;
            let dm3 = blk.mlp.backward(rec, &c.mlp, &r3.dy)?;
            let g3 = Modulate.backward(rec, &c.mod3, &dm3)?;
            add_role(rec, blk, 3, &g3.dshift)?;
            add_role(rec, blk, 4, &g3.dscale)?;
            let dn3 = blk.norm3.backward(rec, &c.n3, &g3.dx)?;
            let dh2 = binary(rec, &r3.dres, &dn3, Binary::Add)?;
            // Cross-attention branch (ungated).
            let cross = c.cross.as_ref().ok_or_else(|| {
                Error::Invalid("generator: a sampling pass keeps nothing for a backward pass".into())
            })?;
            let (dn2, dc) = blk.cross.backward(rec, cross, &dh2.reshape(&[b * k, w])?, &cache.cross_seg)?;
            if let (Some(dctx), Some(dc)) = (&dctx, dc) {
                if dctx_started {
                    binary_into(rec, dctx, &dc, dctx, Binary::Add)?;
                } else {
                    rec.copy(&dc, dctx)?;
                    dctx_started = true;
                }
            }
            let dn2 = blk.norm2.backward(rec, &c.n2, &dn2.reshape(&[b, k, w])?)?;
            let dh1 = binary(rec, &dh2, &dn2, Binary::Add)?;
            // Self-attention branch.
            let r1 = GatedResidual.backward(rec, &c.res1, &dh1)?;
            add_role(rec, blk, 2, &r1.dgate)?;
            let (dm1, _) = blk.attn.backward(rec, &c.attn, &r1.dy.reshape(&[b * k, w])?, &cache.self_seg)?;
            let g1 = Modulate.backward(rec, &c.mod1, &dm1.reshape(&[b, k, w])?)?;
            add_role(rec, blk, 0, &g1.dshift)?;
            add_role(rec, blk, 1, &g1.dscale)?;
            let dn1 = blk.norm1.backward(rec, &c.n1, &g1.dx)?;
            dh = binary(rec, &r1.dres, &dn1, Binary::Add)?;
        }
        // Positions and input.
        let dpos = reduce(rec, &dh, 0, Reduce::Sum)?;
        binary_into(rec, &self.net.positions.grad, &dpos, &self.net.positions.grad, Binary::Add)?;
        self.net.input.param_grads(rec, &cache.input, &dh.reshape(&[b * k, w])?)?;
        // The modulations and the time embedding they read.
        let de = Tensor::empty(&gpu, &[b, w], DType::F32)?;
        let mut de_started = false;
        let roles = self
            .net
            .adaln
            .iter()
            .zip(&dshared)
            .chain(self.net.final_adaln.iter().zip([&gf.dshift, &gf.dscale]));
        for (l, dm) in roles {
            l.grads_into(rec, &cache.e, dm, &de, de_started)?;
            de_started = true;
        }
        self.net.time.backward(rec, &cache.time, &de)?;
        // The condition: its projection, the null rows masked, the RGB embedding's columns.
        if let (Some(cc), Some(dctx)) = (&cache.cond, &dctx) {
            let dbig = self.net.cond_embed.backward(rec, &cc.embed, dctx)?;
            binary_into(rec, &dbig, &cc.keep, &dbig, Binary::Mul)?;
            let drgb = columns(rec, &dbig, self.cfg.dino_width, self.cfg.rgb_width, 1.0)?;
            self.net.rgb.param_grads(rec, &cc.rgb, &drgb)?;
        }
        Ok(())
    }

    /// The flow-matching loss of a micro-batch under given noise `eps [B k, d]`, flow times
    /// `t [B]` and kept conditions: `(weight L, cache, dL/dv)` recorded into `rec`, with no
    /// gradient added (finite-difference checks use it alone). `L` is the sum over the scenes
    /// of each one's mean squared velocity error.
    pub fn flow_loss(
        &self,
        rec: &mut Recorder,
        samples: &[&GenSample],
        eps: &[f32],
        t: &[f32],
        keep: &[bool],
        weight: f32,
    ) -> Result<(Tensor, GenCache, Tensor)> {
        let b = samples.len();
        let (k, d) = (self.cfg.tokens, self.cfg.token_dim);
        if b == 0 || t.len() != b || keep.len() != b || eps.len() != b * k * d {
            return Err(Error::Shape(format!(
                "generator: {b} scenes need {b} flow times, {b} condition flags and {} noise values, got {}, {} and {}",
                b * k * d,
                t.len(),
                keep.len(),
                eps.len()
            )));
        }
        let gpu = rec.gpu().clone();
        let x = Tensor::empty(&gpu, &[b * k, d], DType::F32)?;
        for (s, sample) in samples.iter().enumerate() {
            if sample.tokens.shape() != [k, d] {
                return Err(Error::Shape(format!(
                    "generator: scene {s} has tokens {:?}, the generator makes [{k}, {d}]",
                    sample.tokens
                )));
            }
            rec.copy_rows(&sample.tokens, 0, &x, s * k, k)?;
        }
        let eps = Tensor::from_slice(&gpu, &[b * k, d], eps)?;
        let t_rows: Vec<f32> = t.iter().flat_map(|&v| std::iter::repeat_n(v, k)).collect();
        let t_col = Tensor::from_slice(&gpu, &[b * k, 1], &t_rows)?;
        // x_t = t x + (1 - t) eps = eps + t (x - eps); u = x - eps.
        let u = binary(rec, &x, &eps, Binary::Sub)?;
        let tu = binary(rec, &u, &t_col, Binary::Mul)?;
        let x_t = binary(rec, &eps, &tu, Binary::Add)?;
        let conditions: Vec<&Condition> = samples.iter().map(|s| &s.condition).collect();
        let (ctx, cond) = self.embed_condition(rec, &conditions, keep)?;
        let t_dev = Tensor::from_slice(&gpu, &[b], t)?;
        let rows = vec![self.cond_rows(); b];
        let (v, mut cache) = self.forward(rec, &x_t, &t_dev, Context::Embedded(&ctx), &rows)?;
        cache.cond = Some(cond);
        let (loss, dv) = Loss::mse().weighted(weight).forward_backward_segments(rec, &v, &u, &vec![k; b])?;
        Ok((loss, cache, dv))
    }

    /// The forward and backward passes of a micro-batch, adding `weight` times the gradient of
    /// the sum of the scenes' losses into the store's gradients. Each scene draws its noise,
    /// flow time and condition dropout from its generator.
    pub fn accumulate(&mut self, samples: &[&GenSample], rngs: &mut [Rng], weight: f64) -> Result<Losses> {
        self.record_pass(samples, rngs, weight)?.run(self)
    }

    /// The recording of [`Generator::accumulate`], not yet submitted, and its finish.
    fn record_pass(&mut self, samples: &[&GenSample], rngs: &mut [Rng], weight: f64) -> Result<Ahead<Self>> {
        crate::train::check_micro_batch(samples.len(), rngs.len())?;
        let n = self.cfg.tokens * self.cfg.token_dim;
        let (mut eps, mut t, mut keep) = (Vec::new(), Vec::new(), Vec::new());
        for rng in rngs.iter_mut() {
            eps.extend(rng.normal_vec(n));
            t.push(rng.range(self.cfg.t_min as f64, 1.0 - self.cfg.t_min as f64) as f32);
            keep.push(rng.uniform() >= self.cfg.cond_dropout);
        }
        let mut rec = self.store.recorder()?;
        let mut timer = PassTimer::start(&mut rec);
        let (loss, cache, dv) = self.flow_loss(&mut rec, samples, &eps, &t, &keep, weight as f32)?;
        // The backward pass follows in the same recording: no host wait between the two.
        timer.backward(&mut rec);
        self.backward(&mut rec, &cache, &dv)?;
        // Read back with this recording: no copy and wait of its own on a GPU.
        let loss = rec.read_back(&loss)?;
        timer.end(&mut rec);
        // The step's update, where the trainer asked for it with this pass (ParamStore::update_last).
        self.store.record_update(&mut rec)?;
        Ok(Ahead::one_loss(rec, timer, loss, |model: &mut Generator| &mut model.pass_seconds))
    }

    /// The velocity `[k, token_dim]` of one scene at `x_t` and flow time `t`, in f32: under
    /// `condition` (`keep`), or under the null condition as training's dropout makes it (every
    /// condition row zero, `keep` false). One evaluation of the network, reading the condition
    /// as training does (not through the keys and values the sampler computes once): for tests
    /// that check a sampler's guided step, `v_null + guidance (v_cond - v_null)`, against two
    /// of these, and the training loss against the velocity at its `x_t`.
    pub fn velocity(&self, x_t: &Tensor, t: f32, condition: &Condition, keep: bool) -> Result<Tensor> {
        let gpu = x_t.gpu().clone();
        let mut rec = gpu.recorder()?;
        let (ctx, _) = self.embed_condition(&mut rec, &[condition], &[keep])?;
        let t = Tensor::from_slice(&gpu, &[1], &[t])?;
        let (v, _) = self.forward(&mut rec, x_t, &t, Context::Embedded(&ctx), &[self.cond_rows()])?;
        rec.submit()?;
        Ok(v)
    }

    /// Generates one scene's tokens `[k, token_dim]` for `condition`, normalised (see
    /// [`Generator::denormalise`]): noise from `spec.seed` integrated from `t = 0` to 1. The
    /// condition's keys and values are computed once, before the first step.
    pub fn generate(&self, condition: &Condition, spec: &GenerateSpec) -> Result<Tensor> {
        self.generate_with_progress(condition, spec, &mut |_| {})
    }

    /// [`Generator::generate`], calling `step_done(i)` as the sampler finishes step `i` (of
    /// `spec.steps`, from 1).
    pub fn generate_with_progress(
        &self,
        condition: &Condition,
        spec: &GenerateSpec,
        step_done: &mut dyn FnMut(usize),
    ) -> Result<Tensor> {
        if spec.steps == 0 {
            return Err(Error::Invalid("generation needs at least one integration step".into()));
        }
        if !(spec.guidance.is_finite() && spec.guidance >= 0.0) {
            return Err(Error::Invalid(format!(
                "guidance scale {} is not a finite number >= 0",
                spec.guidance
            )));
        }
        let gpu = condition.patches.gpu().clone();
        let (k, d) = (self.cfg.tokens, self.cfg.token_dim);
        if spec.precision == Precision::F16 {
            let mut rec = gpu.recorder()?;
            self.store.sync_half(&mut rec)?;
            rec.submit()?;
        }
        let guided = spec.guidance != 1.0;
        let rows = self.cond_rows();
        // The condition, and the null condition (one zero row: attending to many equal rows is
        // attending to one) when guiding.
        let mut rec = gpu.recorder()?;
        rec.set_precision(spec.precision);
        let (ctx, _) = self.embed_condition(&mut rec, &[condition], &[true])?;
        let (ctx, lens) = if guided {
            let zero =
                Tensor::from_slice(&gpu, &[1, self.cfg.cond_width()], &vec![0.0f32; self.cfg.cond_width()])?;
            let (null, _) = self.net.cond_embed.forward(&mut rec, &zero)?;
            let both = Tensor::empty(&gpu, &[rows + 1, self.cfg.width], DType::F32)?;
            rec.copy_rows(&ctx, 0, &both, 0, rows)?;
            rec.copy_rows(&null, 0, &both, rows, 1)?;
            (both, vec![rows, 1])
        } else {
            (ctx, vec![rows])
        };
        let kv: Vec<(Tensor, Tensor)> =
            self.net.blocks.iter().map(|b| b.cross.context_kv(&mut rec, &ctx)).collect::<Result<_>>()?;
        rec.submit()?;
        let batch = lens.len();
        let x0 = Tensor::from_slice(&gpu, &[k, d], &Rng::new(spec.seed).normal_vec(k * d))?;
        let per_step = match spec.sampler {
            Sampler::Euler => 1,
            Sampler::Heun => 2,
        };
        let mut calls = 0;
        integrate(&x0, spec.steps, spec.sampler, |rec, x, t| {
            // A step's velocities are recorded before it runs: the previous step is done.
            if calls > 0 && calls % per_step == 0 {
                step_done(calls / per_step);
            }
            calls += 1;
            rec.set_precision(spec.precision);
            let xs = Tensor::empty(&gpu, &[batch * k, d], DType::F32)?;
            for s in 0..batch {
                rec.copy_rows(x, 0, &xs, s * k, k)?;
            }
            let tt = Tensor::from_slice(&gpu, &[batch], &vec![t; batch])?;
            let (v, _) = self.forward(rec, &xs, &tt, Context::Cached(&kv), &lens)?;
            if !guided {
                return Ok(v);
            }
            let (vc, vn) =
                (Tensor::empty(&gpu, &[k, d], DType::F32)?, Tensor::empty(&gpu, &[k, d], DType::F32)?);
            rec.copy_rows(&v, 0, &vc, 0, k)?;
            rec.copy_rows(&v, k, &vn, 0, k)?;
            let diff = binary(rec, &vc, &vn, Binary::Sub)?;
            let scaled = unary(rec, &diff, Unary::Affine(spec.guidance, 0.0))?;
            binary(rec, &vn, &scaled, Binary::Add)
        })
        .inspect(|_| step_done(spec.steps))
    }
}

impl GenCache {
    /// Rows of the condition the cross-attention read.
    fn cross_seg_rows(&self) -> usize {
        self.cond.as_ref().map_or(0, |c| c.keep.shape()[0])
    }
}

crate::train::token_model_files!(Generator, GeneratorConfig, "generator");
crate::train::trainable!(Generator, GenSample;
    fn records_ahead(&self) -> bool {
        true
    }
);
