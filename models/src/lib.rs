pub use velox_engine as engine;

pub mod checkpoint;
pub mod files;
pub mod params;
pub mod schedule;
