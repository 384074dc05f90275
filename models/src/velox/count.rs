//! Parameter counts of the models' parts, from their declarations (the constructors run over
//! stand-ins, see `crate::params`: a device is needed, but no parameter memory): what `velox
//! config NAME --params` prints, to compare configs.
//!
//! Tests: `tests/models/gaussian_decoder.rs`, `voxel_decoder.rs` and `tracker.rs` (the paper
//! configs' parameter counts), `tools/tests/models_cli.rs` (`velox config --params`) and
//! `tests/models/slips.rs` (every model's declarations and their weight decay).

use serde::Serialize;
use velox_engine::{Gpu, Result};

use crate::config::{AutoencoderConfig, VoxelConfig};
use crate::velox::autoencoder::Autoencoder;
use crate::velox::voxels::VoxelDecoder;

/// Scalar parameters of each part and of the whole model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct ParameterCounts {
    pub encoder: usize,
    pub surface: usize,
    pub gaussians: usize,
    pub total: usize,
}

/// The parameter counts of an autoencoder of config `cfg` (checked first), declared on `gpu`
/// (nothing as large as a parameter is allocated).
pub fn parameter_counts(gpu: &Gpu, cfg: &AutoencoderConfig) -> Result<ParameterCounts> {
    let b = Autoencoder::declare(gpu, cfg)?;
    let (encoder, surface, gaussians) = (
        b.num_parameters_under("encoder."),
        b.num_parameters_under("surface."),
        b.num_parameters_under("gaussians."),
    );
    Ok(ParameterCounts { encoder, surface, gaussians, total: b.num_parameters() })
}

/// Scalar parameters of the voxel decoder's stages (the fine one with its voxel head) and in
/// all.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct VoxelParameterCounts {
    pub coarse: usize,
    pub fine: usize,
    pub total: usize,
}

/// The parameter counts of a voxel decoder of config `cfg` (checked first), declared on `gpu`.
pub fn voxel_parameter_counts(gpu: &Gpu, cfg: &VoxelConfig) -> Result<VoxelParameterCounts> {
    let b = VoxelDecoder::declare(gpu, cfg)?;
    let total = b.num_parameters();
    let coarse = b.num_parameters_under("coarse.");
    Ok(VoxelParameterCounts { coarse, fine: total - coarse, total })
}
