pub use velox_data as data;
pub use velox_engine as engine;
pub use velox_io as io;
pub use velox_models as models;
pub use velox_tasks as tasks;
