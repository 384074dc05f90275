pub use velox_engine as engine;

pub mod checkpoint;
pub mod params;
pub mod schedule;
