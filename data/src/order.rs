//! The order in which training visits a dataset's scenes: each pass over the dataset shuffled
//! from `(seed, pass)`, a pure function of the seed and the position in the sequence of passes.
//! It belongs to the trainer (`velox_models::train::order`, where it is documented and tested);
//! the [`crate::Loader`] reads scenes in the same order.

pub use velox_models::train::order::{epoch_order, scene_at, scene_of_step, step_position};
