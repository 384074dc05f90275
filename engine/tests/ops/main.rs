//! The engine's op-level tests: every kernel against its f64 reference, forward and backward,
//! at awkward sizes (empty, one element, past a tile, past a dispatch dimension), the kernel
//! registry against the device's limits, the subgroup facts the kernels rely on, and the
//! rasteriser against closed forms. One binary; each module is one file of tests. `cases` is
//! the harness that runs every op with a reference at several shapes against one table of
//! bounds; the family files hold what a table row cannot say.

#[path = "../common/mod.rs"]
mod common;

mod assign;
mod attention;
mod cases;
mod elementwise;
mod fill_copy;
mod kernels;
mod matmul;
mod raster;
mod recorder;
mod scan_sort;
mod subgroups;
