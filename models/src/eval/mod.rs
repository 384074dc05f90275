//! Evaluation protocols: what `velox eval` measures, as library calls that return the numbers
//! (the command writes and prints them).

pub mod cloth;
pub mod generation;
pub mod recon;
pub mod tracking;
pub mod voxels;
