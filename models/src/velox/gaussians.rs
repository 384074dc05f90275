//! The Velox Gaussian decoder G (docs/models.md, Gaussian decoder; paper Sec. 3): the dynamic
//! tokens and a frame time to 3D Gaussians.
//!
//! - Queries: the occupied voxels of a `grid`^3 grid over [-1, 1]^3 at frame tau (from the
//!   frame's points in training, [`occupied_voxels`]; from the voxel decoder or surface samples
//!   at inference).
//! - The trunk is a [`VoxelPerceiver`] (crate::velox::perceiver): the query features, `blocks`
//!   of cross-attention to the tokens and self-attention in windows of `window_voxels`^3
//!   voxels, a head to G x 14 numbers per voxel (an MLP in the paper config).
//! - Those numbers are activated by [`velox_engine::ops::gaussian_head`] into the rasteriser's
//!   parameters.
//!
//! The backward pass returns the gradient with respect to the tokens, which the encoder needs.
//!
//! Tests: `tests/models/gaussian_decoder.rs` (forward and backward, voxel queries, the head).

use velox_engine::ops::gaussian_head::{head_backward, head_forward, HeadRange, RAW};
use velox_engine::ops::raster::Gaussians;
use velox_engine::{Recorder, Result, Tensor};

use crate::config::GaussianConfig;
use crate::params::Params;
pub use crate::velox::perceiver::VoxelFrames;
use crate::velox::perceiver::{PerceiverCache, PerceiverShape, VoxelPerceiver};
use velox_io::cloud::CHANNELS;

pub struct GaussianDecoder {
    pub cfg: GaussianConfig,
    trunk: VoxelPerceiver,
}

pub struct GaussianCache {
    centres: Tensor,
    trunk: PerceiverCache,
    raw: Tensor,
}

/// Centres (x, y, z) of the voxels of a `grid`^3 grid over [-1, 1]^3 holding at least one
/// point of frame `tau` (rows of the 7-channel cloud whose tau is within 1e-4), in voxel order.
pub fn occupied_voxels(cloud: &[f32], tau: f32, grid: usize) -> Vec<f32> {
    let cell = 2.0 / grid as f32;
    let mut ids: Vec<usize> = cloud
        .chunks(CHANNELS)
        .filter(|p| (p[6] - tau).abs() < 1e-4)
        .map(|p| {
            let c = |v: f32| (((v + 1.0) / cell).floor().max(0.0) as usize).min(grid - 1);
            (c(p[0]) * grid + c(p[1])) * grid + c(p[2])
        })
        .collect();
    ids.sort_unstable();
    ids.dedup();
    let centre = |i: usize| -1.0 + (i as f32 + 0.5) * cell;
    ids.iter()
        .flat_map(|&id| [centre(id / (grid * grid)), centre(id / grid % grid), centre(id % grid)])
        .collect()
}

impl GaussianDecoder {
    /// The trunk's sizes: windows of `window_voxels` voxels, G x 14 numbers per voxel, the
    /// head's last layer small so the first renders start from faint, mid-sized Gaussians at
    /// the centres.
    pub fn shape(cfg: &GaussianConfig) -> PerceiverShape {
        PerceiverShape {
            width: cfg.width,
            heads: cfg.heads,
            blocks: cfg.blocks,
            self_layers: cfg.self_layers,
            ffn_ratio: cfg.ffn_ratio,
            xyz_freqs: cfg.xyz_freqs,
            tau_freqs: cfg.tau_freqs,
            window: 2.0 * cfg.window_voxels as f32 / cfg.grid as f32,
            input_hidden: cfg.input_hidden,
            head_hidden: cfg.head_hidden,
            out: cfg.gaussians_per_voxel * RAW,
            head_std: 0.01,
            query_features: 0,
        }
    }

    /// The decoder, its parameters under `prefix`, reading `token_dim`-wide tokens.
    pub fn new(
        p: &mut Params,
        prefix: &str,
        cfg: &GaussianConfig,
        token_dim: usize,
    ) -> Result<GaussianDecoder> {
        Ok(GaussianDecoder {
            cfg: cfg.clone(),
            trunk: VoxelPerceiver::new(p, prefix, &Self::shape(cfg), token_dim)?,
        })
    }

    fn range(&self) -> HeadRange {
        HeadRange {
            offset_range: self.cfg.offset_range,
            scale_min: self.cfg.scale_min,
            scale_max: self.cfg.scale_max,
        }
    }

    /// Gaussians (`V x G` of them) for `centres` (f32 `[V, 3]`, occupied voxels) at frame `tau`
    /// from `tokens` (`[k, token_dim]`).
    pub fn forward(
        &self,
        rec: &mut Recorder,
        tokens: &Tensor,
        centres: &Tensor,
        tau: f32,
    ) -> Result<(Gaussians, GaussianCache)> {
        let v = centres.shape().first().copied().unwrap_or(0);
        let k = tokens.shape().first().copied().unwrap_or(0);
        self.forward_frames(rec, tokens, centres, &VoxelFrames::single(tokens.gpu(), tau, v, k)?)
    }

    /// [`GaussianDecoder::forward`] of a batch: the voxels' frame times and tokens as `frames`
    /// says (the tokens of every sample of the batch, one after another).
    pub fn forward_frames(
        &self,
        rec: &mut Recorder,
        tokens: &Tensor,
        centres: &Tensor,
        frames: &VoxelFrames,
    ) -> Result<(Gaussians, GaussianCache)> {
        let (raw, trunk) = self.trunk.forward(rec, tokens, centres, frames)?;
        let v = centres.shape()[0];
        let raw = raw.reshape(&[v * self.cfg.gaussians_per_voxel, RAW])?;
        let out = head_forward(rec, &raw, centres, &self.range())?;
        Ok((out, GaussianCache { centres: centres.clone(), trunk, raw }))
    }

    /// Adds every parameter's gradient given the gradients of the Gaussians (the rasteriser's
    /// backward output); returns the gradient with respect to the tokens.
    pub fn backward(&self, rec: &mut Recorder, cache: &GaussianCache, d: &Gaussians) -> Result<Tensor> {
        let d_raw = self.raw_backward(rec, cache, d)?;
        self.trunk.backward(rec, &cache.trunk, &d_raw)
    }

    /// [`GaussianDecoder::backward`] with the tokens' gradient added into `d_tokens` (or
    /// written there, without `accumulate`).
    pub fn backward_into(
        &self,
        rec: &mut Recorder,
        cache: &GaussianCache,
        d: &Gaussians,
        d_tokens: &Tensor,
        accumulate: bool,
    ) -> Result<()> {
        let d_raw = self.raw_backward(rec, cache, d)?;
        self.trunk.backward_into(rec, &cache.trunk, &d_raw, d_tokens, accumulate)
    }

    fn raw_backward(&self, rec: &mut Recorder, cache: &GaussianCache, d: &Gaussians) -> Result<Tensor> {
        let d_raw = head_backward(rec, &cache.raw, &cache.centres, &self.range(), d)?;
        let v = cache.centres.shape()[0];
        d_raw.reshape(&[v, self.cfg.gaussians_per_voxel * RAW])
    }
}
