//! Data tests: procedural and glTF scenes, mesh rendering, point clouds and tracks, the cloth simulation, the dataset format, hostile files, and the token store.
//! One binary per group (ops, models, data, training), so the suite links a few times,
//! not once per file; each module is one file of tests.

#[path = "../common/mod.rs"]
mod common;

mod capture;
mod cloth;
mod data;
mod fuzz;
mod tokens;
