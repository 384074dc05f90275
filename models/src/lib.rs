//! velox-models: the layers and models of Velox, their training primitives and checkpoints.

pub use velox_engine as engine;

pub mod checkpoint;
pub mod config;
pub mod eval;
pub mod layers;
pub mod metrics;
pub mod model;
pub mod params;
pub mod run;
pub mod schedule;
pub mod train;
pub mod velox;

pub use model::Model;
