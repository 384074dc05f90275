pub use velox_engine as engine;
pub use velox_models as models;
