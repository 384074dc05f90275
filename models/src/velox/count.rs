//! Parameter counts of the models' parts, from the parameter declarations alone (no device
//! memory): what `velox config NAME --params` prints, to compare configs.

use serde::Serialize;
use velox_engine::Result;

use crate::config::{AutoencoderConfig, VoxelConfig};
use crate::params::ParamStore;
use crate::velox::encoder::Encoder;
use crate::velox::gaussians::GaussianDecoder;
use crate::velox::surface::SurfaceDecoder;
use crate::velox::voxels::VoxelDecoder;

/// Scalar parameters of each part and of the whole model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct ParameterCounts {
    pub encoder: usize,
    pub surface: usize,
    pub gaussians: usize,
    pub total: usize,
}

/// The parameter counts of an autoencoder of config `cfg` (checked first).
pub fn parameter_counts(cfg: &AutoencoderConfig) -> Result<ParameterCounts> {
    cfg.validate()?;
    let (mut e, mut s, mut g) = (ParamStore::builder(), ParamStore::builder(), ParamStore::builder());
    Encoder::register(&mut e, "encoder", &cfg.encoder)?;
    SurfaceDecoder::register(&mut s, "surface", &cfg.surface, cfg.encoder.token_dim)?;
    GaussianDecoder::register(&mut g, "gaussians", &cfg.gaussians, cfg.encoder.token_dim)?;
    let (encoder, surface, gaussians) = (e.num_parameters(), s.num_parameters(), g.num_parameters());
    Ok(ParameterCounts { encoder, surface, gaussians, total: encoder + surface + gaussians })
}

/// Scalar parameters of the voxel decoder's stages (the fine one with its voxel head) and in
/// all.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct VoxelParameterCounts {
    pub coarse: usize,
    pub fine: usize,
    pub total: usize,
}

/// The parameter counts of a voxel decoder of config `cfg` (checked first).
pub fn voxel_parameter_counts(cfg: &VoxelConfig) -> Result<VoxelParameterCounts> {
    cfg.validate()?;
    let mut b = ParamStore::builder();
    VoxelDecoder::register(&mut b, cfg)?;
    let total = b.num_parameters();
    let coarse = b.num_parameters_under("coarse.");
    Ok(VoxelParameterCounts { coarse, fine: total - coarse, total })
}
