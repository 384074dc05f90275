//! velox-data: the training data of Velox, made on the engine.
//!
//! Velox learns from dynamic colour point clouds back-projected from multiview RGBD videos of
//! animated objects, and from images of the same objects (docs/models.md, Data conventions). The
//! paper used Objaverse, which cannot be had here, so this crate makes its own scenes and
//! imports real animated assets:
//!
//! - [`procedural`]: seeded animated objects (walkers, arms, pendulums, bending, twisting and
//!   pulsing shapes, tumbling bodies, parts that come and go), textured by [`texture`];
//! - [`gltf_import`]: glTF 2.0 files (meshes, node hierarchy, skins, morph targets, base-colour
//!   textures) sampled at 24 frames, read by [`gltf_load`] (URIs only inside the file's folder)
//!   and checked by [`gltf_validate`] first;
//! - both give an [`AnimatedMesh`] ([`mesh`]) normalised into [-1, 1]^3 over the clip;
//! - [`raster`] renders it on the engine with a compute rasteriser (`shaders/mesh_raster.wgsl`)
//!   from the cameras of [`camera`]: RGB, depth, triangle id and barycentrics;
//! - [`pipeline`] turns the renders into point clouds, occupancy and tracks;
//! - [`cloth`]: garments folded and dropped by the engine's cloth solver, as animated meshes;
//! - [`rgbd`] reads RGBD videos and back-projects them (the tracking task's input);
//! - [`format`] writes and reads the dataset.
//!
//! It names no model: what feeds a dataset to a model (the trainer's scene sources, the
//! background loader, the token store's encoding pass, the generators' condition frames) is
//! in `velox-tasks`, above both. It is its own crate because it brings dependencies the
//! runtime and the models do not need:
//! `gltf` (the glTF 2.0 document and its accessor readers, for skins, animations and
//! morph targets), and `image` (PNG and JPEG for textures and the supervision views).

pub mod camera;
pub mod capture;
pub mod cloth;
pub mod format;
pub mod gltf_import;
pub mod gltf_load;
pub mod gltf_validate;
pub mod math;
pub mod mesh;
pub mod pipeline;
pub mod procedural;
pub mod raster;
pub mod rgbd;
pub mod surface;
pub mod texture;
pub mod video;

pub use camera::Camera;
pub use format::{read_scene, Scene, SceneMeta};
pub use mesh::{AnimatedMesh, Texture};
pub use pipeline::{render_scene, SceneArrays, SynthOptions};

use std::fmt;

/// Errors of the data crate: bad input names the file or value, device errors pass through.
#[derive(Debug)]
pub enum DataError {
    Engine(velox_engine::Error),
    /// A file could not be read or written.
    Io(String),
    /// Input that does not make a scene (a corrupt file, an empty mesh, a bad value).
    Invalid(String),
}

pub type DataResult<T> = Result<T, DataError>;

impl fmt::Display for DataError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DataError::Engine(e) => write!(f, "{e}"),
            DataError::Io(m) => write!(f, "{m}"),
            DataError::Invalid(m) => write!(f, "invalid input: {m}"),
        }
    }
}

impl std::error::Error for DataError {}

/// Data errors where the trainer and the models expect engine errors: the same words.
impl From<DataError> for velox_engine::Error {
    fn from(e: DataError) -> velox_engine::Error {
        match e {
            DataError::Engine(e) => e,
            DataError::Io(m) => velox_engine::Error::Io(m),
            DataError::Invalid(m) => velox_engine::Error::Invalid(m),
        }
    }
}

impl From<velox_engine::Error> for DataError {
    fn from(e: velox_engine::Error) -> DataError {
        DataError::Engine(e)
    }
}
