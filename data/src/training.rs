//! A scene read from disk as the autoencoder trains on it: the cloud, the supervision cameras
//! in the rasteriser's form, and the supervision images as f32 RGB in [0, 1].

use velox_engine::ops::raster;
use velox_engine::Gpu;
use velox_models::velox::autoencoder::TrainScene;

use crate::camera::Camera;
use crate::format::Scene;
use crate::{DataError, DataResult};

impl Camera {
    /// The same pinhole camera for the Gaussian rasteriser (the conventions agree: world to
    /// camera rows, x right, y down, z forward, pixel centres at +0.5).
    pub fn to_raster(&self) -> raster::Camera {
        raster::Camera {
            width: self.width,
            height: self.height,
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            rotation: self.rotation,
            translation: self.translation,
        }
    }
}

/// Uploads a scene read with its images (`read_scene(dir, true)`) for training.
pub fn train_scene(gpu: &Gpu, scene: &Scene) -> DataResult<TrainScene> {
    if scene.supervision.is_empty() {
        return Err(DataError::Invalid(format!(
            "{}: the scene was read without its images; training needs them",
            scene.dir.display()
        )));
    }
    let cloud: Vec<f32> = scene.points.iter().flatten().copied().collect();
    let cameras: Vec<raster::Camera> = scene.cameras.supervision.iter().map(Camera::to_raster).collect();
    let images =
        scene.supervision.iter().map(|img| img.iter().map(|&b| b as f32 / 255.0).collect()).collect();
    TrainScene::new(gpu, cloud, cameras, images)
        .map_err(|e| DataError::Invalid(format!("{}: {e}", scene.dir.display())))
}
