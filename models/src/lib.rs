pub use velox_engine as engine;
pub mod layers;
