//! Training tests: the trainer (batches, accumulation, resuming, bit-exact runs) and a transformer trained end to end.
//! One binary per group (ops, models, data, training), so the suite links a few times,
//! not once per file; each module is one file of tests.

#[path = "../common/mod.rs"]
mod common;

mod train_transformer;
mod trainer;
