//! Training tests: the optimiser, losses and parameter store against their references, f16 training against f32, the trainer (batches, accumulation, resuming, bit-exact runs) and a transformer trained end to end.
//! One binary per group (ops, models, data, training), so the suite links a few times,
//! not once per file; each module is one file of tests.

#[path = "../common/mod.rs"]
mod common;

mod mixed_precision;
mod train_primitives;
mod train_transformer;
mod trainer;
