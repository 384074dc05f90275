pub use velox_data as data;
pub use velox_engine as engine;
pub use velox_models as models;
