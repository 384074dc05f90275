//! Model tests: the layers (linear stacks, norms, feed-forwards, attention layers) against their references, each model's composed backward against finite differences, learning against the trivial model, the paper config's parameter count, and its files.
//! One binary per group (ops, models, data, training), so the suite links a few times,
//! not once per file; each module is one file of tests.

#[path = "../common/mod.rs"]
mod common;

mod attention_layer;
mod autoencoder;
mod dinov2;
mod encoder;
mod eval_alignment;
mod gaussian_decoder;
mod generator;
mod layers;
mod slips;
mod surface_decoder;
mod tracker;
mod voxel_decoder;
