//! The Velox models built from the layers (MODELS.md).

pub mod surface;
