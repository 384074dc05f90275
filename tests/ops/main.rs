//! Op-level tests: every kernel against its f64 reference, forward and backward, at awkward sizes; the raster, sort, scan, attention and matmul families; the training primitives, f16 paths and the cloth solver.
//! One binary per group (ops, models, data, training), so the suite links a few times,
//! not once per file; each module is one file of tests.

#[path = "../common/mod.rs"]
mod common;

mod assign;
mod attention;
mod attention_layer;
mod cloth;
mod elementwise;
mod fill_copy;
mod kernels;
mod layers;
mod matmul;
mod mixed_precision;
mod raster;
mod scan_sort;
mod subgroups;
mod train_primitives;
