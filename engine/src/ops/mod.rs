//! Ops: each file holds one op family's host side (validation, dispatch) and its f64 CPU
//! reference (`reference` submodule), next to `shaders/<op>.wgsl`.

pub mod adaln;
pub mod adamw;
pub mod assign;
pub mod attention;
pub mod binary;
pub mod cast;
pub mod cloth;
pub mod columns;
pub mod concat;
pub mod fill;
pub mod fourier;
pub mod fps;
pub mod gather;
pub mod gaussian_head;
pub mod gelu;
pub mod layernorm;
pub mod loss;
pub mod matmul;
pub mod norm;
pub mod raster;
pub mod reduce;
pub mod rmsnorm;
pub mod scan;
pub mod scatter_add;
pub mod softmax;
pub mod sort;
pub mod subgroup_probe;
pub mod swiglu;
pub mod unary;
pub mod voxel_head;
pub mod window;
