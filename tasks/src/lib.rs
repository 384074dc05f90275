//! velox-tasks: what joins a dataset to a model, above the data and the models crates (neither
//! of which names the other).
//!
//! - [`training`] gives scenes to the trainer: as the autoencoder trains on them
//!   ([`train_scene`], [`SceneFolders`]), or as stored tokens and occupancy for the models
//!   downstream of the frozen encoder ([`TokenScenes`], [`TrackScenes`], [`GenScenes`]);
//! - [`loader`] reads a dataset's scenes in the background, in the trainer's order
//!   (`velox_models::train::order`);
//! - [`encode`] stores a trained encoder's tokens of every scene once (the token store);
//! - [`condition`] reads a video's frames as the generators' condition, normalised as DINOv2
//!   expects, and [`generate`] loads a generator with the models it was trained against and
//!   makes tokens from them;
//! - [`run`] starts a training run (new, resumed, or from another run's parameters) and
//!   trains it: the one way every front end trains a model;
//! - [`export`] writes per-frame Gaussians in the files other viewers play;
//! - [`tapvid3d`] scores any tracker's predictions on TAPVid-3D's own files;
//! - [`track`] follows query points through an RGBD video with a trained tracker;
//! - [`view`] shows a 4D result in a browser (the page, its frames, a small server);
//! - [`evaluate`] runs the evaluations of the models downstream of the encoder scene by scene
//!   (the voxel decoder, the tracker, the generator as images and as falling cloth).

pub mod condition;
pub mod encode;
pub mod evaluate;
pub mod export;
pub mod generate;
pub mod loader;
pub mod run;
pub mod tapvid3d;
pub mod track;
pub mod training;
pub mod view;

pub use loader::{Loader, LoaderOptions};
pub use training::{train_scene, GenScenes, SceneFolders, TokenScenes, TrackScenes};
