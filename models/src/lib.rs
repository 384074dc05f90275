pub use velox_engine as engine;
