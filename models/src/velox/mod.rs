//! The Velox models (paper sections 3.1 to 3.3; sizes in `crate::config`).

pub mod autoencoder;
pub mod blocks;
pub mod count;
pub mod decode;
pub mod dinov2;
pub mod encoder;
pub mod gaussians;
pub mod generator;
pub mod perceiver;
pub mod surface;
pub mod tokens;
pub mod tracker;
pub mod voxels;
