//! Ops: each file holds one op family's host side (validation, dispatch) and its f64 CPU
//! reference (`reference` submodule), next to `shaders/<op>.wgsl`.

pub mod fill;
pub mod matmul;
