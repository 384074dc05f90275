//! The voxel decoder (docs/models.md, Voxel decoder; the occupied voxels of a frame predicted
//! from the dynamic tokens, so Gaussians decode without sampling the surface ODE).
//!
//! Tests: `tests/models/voxel_decoder.rs` (both stages, learning against the trivial model, other
//! scenes' tokens), `tests/models/slips.rs` (the dilation reaching the fine stage alone).

use velox_engine::ops::adamw::AdamWConfig;
use velox_engine::ops::attention::Segments;
use velox_engine::ops::gelu::gelu_backward;
use velox_engine::ops::reduce::{reduce, Reduce};
use velox_engine::ops::voxel_head;
use velox_engine::rng::Rng;
use velox_engine::Recorder;
use velox_engine::{DType, Error, Gpu, Readback, Result, Tensor};

use crate::config::{OccupancyLoss, VoxelConfig, VoxelStageConfig};
use crate::layers::linear::LinearCache;
use crate::layers::{Fourier, Linear, Loss};
use crate::params::{build, declare, ParamBuilder, ParamStore, Params};
use crate::train::{Ahead, Finish, Losses, PassSeconds, PassTimer};
use crate::velox::autoencoder::tau_of;
use crate::velox::blocks::linear;
use crate::velox::perceiver::{PerceiverShape, VoxelFrames, VoxelPerceiver};

/// Side of the occupancy grid over [-1, 1]^3 the data stores and the decoder predicts.
pub const GRID: usize = 64;
/// 64-bit words of one frame's occupancy: voxel (x, y, z) is bit `i % 64` of word `i / 64`,
/// `i = x + 64 (y + 64 z)` (the dataset's `occupancy.bin` layout).
pub const FRAME_WORDS: usize = GRID * GRID * GRID / 64;

/// What the voxel decoder trains on from one scene: its stored tokens and its occupancy.
pub struct VoxelSample {
    /// The scene's tokens `[k, token_dim]` on the device (the frozen encoder's, from `velox
    /// encode`).
    pub tokens: Tensor,
    /// [`FRAME_WORDS`] words per frame, every frame of the clip.
    pub occupancy: Vec<u64>,
}

impl VoxelSample {
    /// Checks the shapes: tokens `[k > 0, d > 0]` f32, whole frames of occupancy.
    pub fn new(tokens: Tensor, occupancy: Vec<u64>) -> Result<VoxelSample> {
        let ok_tokens = matches!(tokens.shape(), [k, d] if *k > 0 && *d > 0)
            && tokens.dtype() == velox_engine::DType::F32;
        if !ok_tokens {
            return Err(Error::Shape(format!("voxel sample: tokens must be f32 [k, d], got {tokens:?}")));
        }
        if occupancy.is_empty() || !occupancy.len().is_multiple_of(FRAME_WORDS) {
            return Err(Error::Shape(format!(
                "voxel sample: {} occupancy words are not whole frames of {FRAME_WORDS}",
                occupancy.len()
            )));
        }
        Ok(VoxelSample { tokens, occupancy })
    }

    /// Frames of occupancy.
    pub fn frames(&self) -> usize {
        self.occupancy.len() / FRAME_WORDS
    }

    /// Whether voxel `(x, y, z)` is occupied at frame `f`.
    pub fn occupied(&self, f: usize, x: usize, y: usize, z: usize) -> bool {
        let i = x + GRID * (y + GRID * z);
        self.occupancy[f * FRAME_WORDS + i / 64] >> (i % 64) & 1 == 1
    }
}

/// The `model` a checkpoint of the voxel decoder names.
pub const MODEL_KIND: &str = "velox voxel decoder";

/// Occupied-voxel predictions of one frame, and how much of the grid the fine stage refined.
#[derive(Clone, Debug, PartialEq)]
pub struct Prediction {
    /// [`FRAME_WORDS`] words of occupancy bits.
    pub occupancy: Vec<u64>,
    /// The coarse cells the fine stage refined (those the coarse stage called occupied), in
    /// increasing order.
    pub refined: Vec<usize>,
}

/// The voxel decoder: a coarse [`VoxelPerceiver`] over every cell of a `cells`^3 grid that
/// predicts whether the cell holds surface, and a fine one over those cells alone that
/// predicts each one's voxels of the 64^3 grid (see `crate::config::VoxelConfig`).
///
/// Training ([`VoxelDecoder::accumulate`]): per scene `frames_per_sample` frames; the coarse
/// stage learns every cell's label (any voxel occupied), the fine stage the voxels of the
/// occupied cells and of the cells within `dilate` of one (the true cells stand in for the
/// coarse stage's choice, so the two stages train at once). Each loss is a scene's mean over
/// its cells or its refined voxels. Prediction ([`VoxelDecoder::predict`]): the cells above
/// `cell_threshold`, then their voxels above `threshold`. The tokens are the frozen encoder's: the decoder
/// computes no gradient for them that anything uses.
pub struct VoxelDecoder {
    pub cfg: VoxelConfig,
    pub store: ParamStore,
    coarse: VoxelPerceiver,
    fine: VoxelPerceiver,
    head: VoxelHead,
    pub adamw: AdamWConfig,
    pass_seconds: PassSeconds,
}

/// Centre of coarse cell `c` (`c = i + cells (j + cells l)`) in [-1, 1]^3.
fn cell_centre(c: usize, cells: usize) -> [f32; 3] {
    let side = 2.0 / cells as f32;
    [c % cells, c / cells % cells, c / (cells * cells)].map(|i| -1.0 + (i as f32 + 0.5) * side)
}

/// The voxel index (`x + 64 (y + 64 z)`) of voxel `v` (`dx + s (dy + s dz)`) of cell `c`.
pub fn voxel_of(c: usize, v: usize, cells: usize) -> usize {
    let s = GRID / cells;
    let (i, j, l) = (c % cells, c / cells % cells, c / (cells * cells));
    let (dx, dy, dz) = (v % s, v / s % s, v / (s * s));
    (i * s + dx) + GRID * ((j * s + dy) + GRID * (l * s + dz))
}

fn bit(words: &[u64], i: usize) -> bool {
    words[i / 64] >> (i % 64) & 1 == 1
}

/// Each coarse cell's label: whether any of its voxels is occupied in `frame` (one frame's
/// words).
pub fn cell_labels(frame: &[u64], cells: usize) -> Vec<bool> {
    let per = (GRID / cells).pow(3);
    (0..cells.pow(3)).map(|c| (0..per).any(|v| bit(frame, voxel_of(c, v, cells)))).collect()
}

/// `cells` (flags over the cells^3 cells) grown by `d` cells in every direction (a cube).
pub fn dilate(flags: &[bool], cells: usize, d: usize) -> Vec<bool> {
    if d == 0 {
        return flags.to_vec();
    }
    let mut out = vec![false; flags.len()];
    for (c, &on) in flags.iter().enumerate() {
        if !on {
            continue;
        }
        let (i, j, l) = (c % cells, c / cells % cells, c / (cells * cells));
        for l2 in l.saturating_sub(d)..(l + d + 1).min(cells) {
            for j2 in j.saturating_sub(d)..(j + d + 1).min(cells) {
                for i2 in i.saturating_sub(d)..(i + d + 1).min(cells) {
                    out[i2 + cells * (j2 + cells * l2)] = true;
                }
            }
        }
    }
    out
}

/// Centres `[V * 3]` of the voxels of a `grid`^3 grid (64 or a divisor) that hold an occupied
/// voxel of one frame's words, in the order of [`crate::velox::gaussians::occupied_voxels`]
/// (x, then y, then z), so the Gaussian decoder can decode predicted voxels at its own grid.
pub fn occupied_centres(frame: &[u64], grid: usize) -> Result<Vec<f32>> {
    if grid == 0 || !GRID.is_multiple_of(grid) {
        return Err(Error::Invalid(format!("occupied voxels at a grid of {grid}: it must divide {GRID}")));
    }
    let s = GRID / grid;
    let mut ids: Vec<usize> = (0..GRID * GRID * GRID)
        .filter(|&i| bit(frame, i))
        .map(|i| {
            let (x, y, z) = (i % GRID / s, i / GRID % GRID / s, i / (GRID * GRID) / s);
            (x * grid + y) * grid + z
        })
        .collect();
    ids.sort_unstable();
    ids.dedup();
    let cell = 2.0 / grid as f32;
    let centre = |i: usize| -1.0 + (i as f32 + 0.5) * cell;
    Ok(ids
        .iter()
        .flat_map(|&id| [centre(id / (grid * grid)), centre(id / grid % grid), centre(id % grid)])
        .collect())
}

/// The fine stage's head: logit(cell c, voxel v) = w . GELU(a_c + b_v) + bias, with a_c the fine
/// trunk's feature of the cell and b_v a linear embedding of the voxel's Fourier-embedded offset
/// in its cell. A smooth function of where the voxel lies, given the cell, which a head of
/// (64 / cells)^3 separate outputs per cell learned far more slowly (its fine loss stayed
/// at the label prior over a hundred steps of one scene).
struct VoxelHead {
    /// `[s^3, F]`: the offsets' features, fixed.
    offsets: Tensor,
    /// `[s^3, 3]`: the offsets themselves, which `cell_directions` weighs the directions by.
    xyz: Tensor,
    directions: bool,
    embed: Linear,
    out: Linear,
}

struct VoxelHeadCache {
    embed: LinearCache,
    /// The cells' features and the offsets' embedding the pre-activation was made of.
    features: Tensor,
    embedded: Tensor,
    pre: Tensor,
    out: LinearCache,
}

/// Width of the fine trunk's output per cell: the head's hidden width, and with
/// `cell_directions` three more of it (a direction per hidden unit).
fn fine_out(cfg: &VoxelConfig) -> usize {
    cfg.voxel_hidden * if cfg.cell_directions { 4 } else { 1 }
}

impl VoxelHead {
    /// The head, its parameters under `prefix` (`.embed`, `.out`).
    fn new(p: &mut Params, prefix: &str, cfg: &VoxelConfig) -> Result<VoxelHead> {
        let gpu = p.gpu().clone();
        let gpu = &gpu;
        let embed = linear(p, &format!("{prefix}.embed"), 3 + 6 * cfg.offset_freqs, cfg.voxel_hidden, true)?;
        let out = linear(p, &format!("{prefix}.out"), cfg.voxel_hidden, 1, true)?;
        // Each voxel's offset from its cell's centre, in half-cells: in (-1, 1) on each axis.
        let s = cfg.cell_side();
        let offset = |d: usize| (2 * d + 1) as f32 / s as f32 - 1.0;
        let xyz: Vec<f32> =
            (0..s * s * s).flat_map(|v| [offset(v % s), offset(v / s % s), offset(v / (s * s))]).collect();
        let fourier = Fourier::octaves(gpu, 3, cfg.offset_freqs, true)?;
        let mut rec = gpu.recorder()?;
        let (offsets, _) = fourier.forward(&mut rec, &Tensor::from_slice(gpu, &[s * s * s, 3], &xyz)?)?;
        rec.submit()?;
        Ok(VoxelHead {
            offsets,
            xyz: Tensor::from_slice(gpu, &[s * s * s, 3], &xyz)?,
            directions: cfg.cell_directions,
            embed,
            out,
        })
    }

    /// Logits `[n, s^3]` from the cells' features (`[n, voxel_hidden]`, or with cell
    /// directions `[n, 4 voxel_hidden]`: `a_c`, then the directions' x, y and z components).
    fn forward(&self, rec: &mut Recorder, features: &Tensor) -> Result<(Tensor, VoxelHeadCache)> {
        let per = self.offsets.shape()[0];
        let (b, embed) = self.embed.forward(rec, &self.offsets)?;
        let h = b.shape()[1];
        let n = features.shape()[0];
        // The pre-activation and its GELU in one pass (`shaders/voxel_head.wgsl`).
        let (pre, g) = voxel_head::forward(rec, features, &b, &self.xyz, self.directions)?;
        let (logits, out) = self.out.forward(rec, &g.reshape(&[n * per, h])?)?;
        let cache = VoxelHeadCache { embed, features: features.clone(), embedded: b, pre, out };
        Ok((logits.reshape(&[n, per])?, cache))
    }

    /// Adds the head's parameter gradients; returns the gradient of the cells' features.
    fn backward(&self, rec: &mut Recorder, cache: &VoxelHeadCache, d_logits: &Tensor) -> Result<Tensor> {
        let [n, per, h] = *cache.pre.shape() else { unreachable!("the head's pre-activation is 3-D") };
        let dg = self.out.backward(rec, &cache.out, &d_logits.reshape(&[n * per, 1])?)?;
        let dpre = gelu_backward(rec, &cache.pre, &dg.reshape(&[n, per, h])?)?;
        let db = reduce(rec, &dpre, 0, Reduce::Sum)?;
        self.embed.param_grads(rec, &cache.embed, &db)?;
        voxel_head::backward(rec, &cache.features, &cache.embedded, &self.xyz, self.directions, &dpre)
    }
}

/// Rows of `[n, width]` as one tensor from host rows (`n = data.len() / width`).
fn rows(gpu: &Gpu, data: &[f32], width: usize) -> Result<Tensor> {
    Tensor::from_slice(gpu, &[data.len() / width, width], data)
}

impl VoxelDecoder {
    /// The sizes of a stage: windows of `window_cells` cells, `out` logits per cell.
    fn shape(cfg: &VoxelConfig, stage: &VoxelStageConfig, out: usize) -> PerceiverShape {
        PerceiverShape {
            width: stage.width,
            heads: stage.heads,
            blocks: stage.blocks,
            self_layers: stage.self_layers,
            ffn_ratio: stage.ffn_ratio,
            xyz_freqs: cfg.xyz_freqs,
            tau_freqs: cfg.tau_freqs,
            window: 2.0 * stage.window_cells as f32 / cfg.cells as f32,
            input_hidden: stage.input_hidden,
            head_hidden: stage.head_hidden,
            out,
            head_std: 0.01,
            query_features: 0,
        }
    }

    /// The two stages and the voxel head.
    fn parts(p: &mut Params, cfg: &VoxelConfig) -> Result<(VoxelPerceiver, VoxelPerceiver, VoxelHead)> {
        let coarse = VoxelPerceiver::new(p, "coarse", &Self::shape(cfg, &cfg.coarse, 1), cfg.token_dim)?;
        let fine =
            VoxelPerceiver::new(p, "fine", &Self::shape(cfg, &cfg.fine, fine_out(cfg)), cfg.token_dim)?;
        Ok((coarse, fine, VoxelHead::new(p, "voxel_head", cfg)?))
    }

    /// The parameters a config declares, without allocating them.
    pub fn declare(gpu: &Gpu, cfg: &VoxelConfig) -> Result<ParamBuilder> {
        cfg.validate()?;
        declare(gpu, |p| Self::parts(p, cfg))
    }

    /// A freshly initialised decoder (parameters from `seed`): `coarse.*`, `fine.*`,
    /// `voxel_head.*`.
    pub fn new(gpu: &Gpu, cfg: &VoxelConfig, seed: u64) -> Result<VoxelDecoder> {
        cfg.validate()?;
        let ((coarse, fine, head), store) = build(gpu, seed, |p| Self::parts(p, cfg))?;
        Ok(VoxelDecoder {
            cfg: cfg.clone(),
            store,
            coarse,
            fine,
            head,
            adamw: AdamWConfig::default(),
            pass_seconds: PassSeconds::default(),
        })
    }

    fn check_tokens(&self, tokens: &Tensor) -> Result<usize> {
        crate::velox::tokens::check_shape("voxel decoder", tokens, self.cfg.token_dim)
    }

    /// The frames a sample trains on: `frames_per_sample` distinct frames drawn from `rng`.
    fn draw_frames(&self, frames: usize, rng: &mut Rng) -> Vec<usize> {
        let mut all: Vec<usize> = (0..frames).collect();
        let f = self.cfg.frames_per_sample.clamp(1, frames);
        for i in 0..f {
            let j = i + rng.below((frames - i) as u32) as usize;
            all.swap(i, j);
        }
        all.truncate(f);
        all
    }

    /// The forward and backward passes of a micro-batch of scenes, adding `weight` times the
    /// gradient of the sum of their losses into the store's gradients; `rngs` holds each
    /// scene's generator. Returns the terms ("total", "coarse", "fine"), summed over the
    /// scenes, times `weight`.
    pub fn accumulate(&mut self, samples: &[&VoxelSample], rngs: &mut [Rng], weight: f64) -> Result<Losses> {
        self.record_pass(samples, rngs, weight)?.run(self)
    }

    /// The recording of [`VoxelDecoder::accumulate`], not yet submitted, and its finish.
    fn record_pass(
        &mut self,
        samples: &[&VoxelSample],
        rngs: &mut [Rng],
        weight: f64,
    ) -> Result<Ahead<Self>> {
        crate::train::check_micro_batch(samples.len(), rngs.len())?;
        let gpu = samples[0].tokens.gpu().clone();
        let (cells, weight) = (self.cfg.cells, weight as f32);
        let n_cells = cells.pow(3);
        let per_cell = self.cfg.cell_side().pow(3);
        let centres: Vec<f32> = (0..n_cells).flat_map(|c| cell_centre(c, cells)).collect();

        // Every scene's tokens, one after another, and per scene its frames' cells.
        let token_counts =
            samples.iter().map(|s| self.check_tokens(&s.tokens)).collect::<Result<Vec<_>>>()?;
        let tokens = Tensor::empty(&gpu, &[token_counts.iter().sum(), self.cfg.token_dim], DType::F32)?;
        let mut rec = self.store.recorder()?;
        let mut timer = PassTimer::start(&mut rec);
        let mut at = 0;
        for (s, &k) in samples.iter().zip(&token_counts) {
            rec.copy_rows(&s.tokens, 0, &tokens, at, k)?;
            at += k;
        }
        let (mut coarse_pos, mut coarse_labels, mut coarse_groups, mut coarse_rows) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let (mut fine_pos, mut fine_labels, mut fine_groups, mut fine_rows) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (s, rng) in samples.iter().zip(rngs.iter_mut()) {
            let frames = self.draw_frames(s.frames(), rng);
            let mut refined = 0;
            for &f in &frames {
                let words = &s.occupancy[f * FRAME_WORDS..(f + 1) * FRAME_WORDS];
                let tau = tau_of(f);
                let labels = cell_labels(words, cells);
                coarse_pos.extend_from_slice(&centres);
                coarse_labels.extend(labels.iter().map(|&l| l as u8 as f32));
                coarse_groups.push((tau, n_cells));
                let chosen = dilate(&labels, cells, self.cfg.dilate);
                let mut count = 0;
                for c in (0..n_cells).filter(|&c| chosen[c]) {
                    fine_pos.extend(cell_centre(c, cells));
                    fine_labels.extend((0..per_cell).map(|v| bit(words, voxel_of(c, v, cells)) as u8 as f32));
                    count += 1;
                }
                fine_groups.push((tau, count));
                refined += count;
            }
            coarse_rows.push(frames.len() * n_cells);
            fine_rows.push(refined);
        }
        let loss = match self.cfg.loss {
            OccupancyLoss::Bce => Loss::bce_with_logits(),
            OccupancyLoss::Focal { gamma } => Loss::focal(gamma),
        };

        // Coarse stage over every cell: a scene's loss is the mean over its frames' cells.
        let segments = |rows: &[usize]| Segments::from_lengths(&gpu, rows, &token_counts);
        let coarse_frames = VoxelFrames { groups: coarse_groups, segments: segments(&coarse_rows)? };
        let (logits, coarse_cache) =
            self.coarse.forward(&mut rec, &tokens, &rows(&gpu, &coarse_pos, 3)?, &coarse_frames)?;
        let (coarse_loss, d_coarse) = loss.weighted(weight).forward_backward_segments(
            &mut rec,
            &logits,
            &rows(&gpu, &coarse_labels, 1)?,
            &coarse_rows,
        )?;
        // Fine stage over the true cells and their neighbours: the mean over the scene's voxels
        // of those cells.
        let fine = if fine_pos.is_empty() {
            None
        } else {
            let fine_frames = VoxelFrames { groups: fine_groups, segments: segments(&fine_rows)? };
            let (features, cache) =
                self.fine.forward(&mut rec, &tokens, &rows(&gpu, &fine_pos, 3)?, &fine_frames)?;
            let (logits, head) = self.head.forward(&mut rec, &features)?;
            let labels = rows(&gpu, &fine_labels, per_cell)?;
            let (l, d) =
                loss.weighted(weight).forward_backward_segments(&mut rec, &logits, &labels, &fine_rows)?;
            Some((l, d, cache, head))
        };
        // The backward pass follows in the same recording: no host wait between the two.
        timer.backward(&mut rec);
        self.coarse.backward(&mut rec, &coarse_cache, &d_coarse)?;
        if let Some((_, d, cache, head)) = &fine {
            let d_features = self.head.backward(&mut rec, head, d)?;
            self.fine.backward(&mut rec, cache, &d_features)?;
        }
        // The losses come back with this recording (no copy and wait of their own on a GPU).
        let coarse = rec.read_back(&coarse_loss)?;
        let fine = fine.as_ref().map(|(l, ..)| rec.read_back(l)).transpose()?;
        timer.end(&mut rec);
        // The step's update, where the trainer asked for it with this pass (ParamStore::update_last).
        self.store.record_update(&mut rec)?;
        let finish: Finish<Self> = Box::new(move |model: &mut Self, finished| {
            timer.add(finished, &mut model.pass_seconds);
            let read = |t: &Readback| -> Result<f64> { Ok(t.read::<f32>()?[0] as f64) };
            let coarse = read(&coarse)?;
            let fine = match &fine {
                Some(l) => read(l)?,
                None => 0.0,
            };
            let total = coarse + fine;
            if !total.is_finite() {
                return Err(Error::Invalid(format!(
                    "the loss became non-finite (coarse {coarse}, fine {fine})"
                )));
            }
            Ok(Losses { terms: vec![("total", total), ("coarse", coarse), ("fine", fine)] })
        });
        Ok(Ahead { rec, finish })
    }

    /// The coarse stage's logits `[F cells^3, 1]` for every cell of each frame time of `taus`
    /// (one scene's `tokens`), recorded into `rec`.
    pub fn coarse_logits(&self, rec: &mut Recorder, tokens: &Tensor, taus: &[f32]) -> Result<Tensor> {
        let k = self.check_tokens(tokens)?;
        let (cells, gpu) = (self.cfg.cells, tokens.gpu());
        let n_cells = cells.pow(3);
        let centres: Vec<f32> = (0..n_cells).flat_map(|c| cell_centre(c, cells)).collect();
        let positions: Vec<f32> = taus.iter().flat_map(|_| centres.iter().copied()).collect();
        let frames = VoxelFrames {
            groups: taus.iter().map(|&t| (t, n_cells)).collect(),
            segments: Segments::dense(gpu, taus.len() * n_cells, k)?,
        };
        Ok(self.coarse.forward(rec, tokens, &rows(gpu, &positions, 3)?, &frames)?.0)
    }

    /// The fine stage's logits `[sum of chosen, (64 / cells)^3]` for the cells `chosen[f]` of
    /// each frame time `taus[f]`, recorded into `rec`; `None` when no cell is chosen.
    pub fn fine_logits(
        &self,
        rec: &mut Recorder,
        tokens: &Tensor,
        taus: &[f32],
        chosen: &[Vec<usize>],
    ) -> Result<Option<Tensor>> {
        let k = self.check_tokens(tokens)?;
        let total: usize = chosen.iter().map(Vec::len).sum();
        if total == 0 {
            return Ok(None);
        }
        let (cells, gpu) = (self.cfg.cells, tokens.gpu());
        let positions: Vec<f32> = chosen.iter().flatten().flat_map(|&c| cell_centre(c, cells)).collect();
        let frames = VoxelFrames {
            groups: taus.iter().zip(chosen).map(|(&t, c)| (t, c.len())).collect(),
            segments: Segments::dense(gpu, total, k)?,
        };
        let (features, _) = self.fine.forward(rec, tokens, &rows(gpu, &positions, 3)?, &frames)?;
        Ok(Some(self.head.forward(rec, &features)?.0))
    }

    /// The occupied voxels of one scene at each frame time of `taus`, from its `tokens`: the
    /// coarse stage over every cell of every frame in one pass, then the fine stage over the
    /// cells above the cell threshold, again every frame at once.
    pub fn predict(&self, tokens: &Tensor, taus: &[f32]) -> Result<Vec<Prediction>> {
        self.check_tokens(tokens)?;
        if taus.is_empty() {
            return Ok(Vec::new());
        }
        let gpu = tokens.gpu().clone();
        let cells = self.cfg.cells;
        let n_cells = cells.pow(3);
        let per_cell = self.cfg.cell_side().pow(3);
        let logit_of = |p: f32| (p / (1.0 - p)).ln();
        let (cell_logit, logit) = (logit_of(self.cfg.cell_threshold), logit_of(self.cfg.threshold));
        let mut rec = gpu.recorder()?;
        let coarse = self.coarse_logits(&mut rec, tokens, taus)?;
        rec.submit()?;
        let coarse: Vec<f32> = coarse.read()?;
        let chosen: Vec<Vec<usize>> = (0..taus.len())
            .map(|f| (0..n_cells).filter(|&c| coarse[f * n_cells + c] > cell_logit).collect())
            .collect();
        let mut out: Vec<Prediction> = chosen
            .iter()
            .map(|c| Prediction { occupancy: vec![0; FRAME_WORDS], refined: c.clone() })
            .collect();
        let mut rec = gpu.recorder()?;
        let Some(fine) = self.fine_logits(&mut rec, tokens, taus, &chosen)? else { return Ok(out) };
        rec.submit()?;
        let fine: Vec<f32> = fine.read()?;
        let mut row = 0;
        for (pred, cells_of) in out.iter_mut().zip(&chosen) {
            for &c in cells_of {
                for v in 0..per_cell {
                    if fine[row * per_cell + v] > logit {
                        let i = voxel_of(c, v, cells);
                        pred.occupancy[i / 64] |= 1 << (i % 64);
                    }
                }
                row += 1;
            }
        }
        Ok(out)
    }
}

crate::train::token_model_files!(VoxelDecoder, VoxelConfig, "voxel decoder");
crate::train::trainable!(VoxelDecoder, VoxelSample;
    fn records_ahead(&self) -> bool {
        true
    }
);
