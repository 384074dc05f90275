//! A scene read from disk as the autoencoder trains on it: the cloud, the supervision cameras
//! in the rasteriser's form, and the supervision images as f32 RGB in [0, 1].

use velox_engine::Gpu;
use velox_models::velox::autoencoder::TrainScene;

use crate::format::Scene;
use crate::{DataError, DataResult};

/// Uploads a scene read with its images (`read_scene(dir, true)`) for training.
pub fn train_scene(gpu: &Gpu, scene: &Scene) -> DataResult<TrainScene> {
    if scene.supervision.is_empty() {
        return Err(DataError::Invalid(format!(
            "{}: the scene was read without its images; training needs them",
            scene.dir.display()
        )));
    }
    let cloud: Vec<f32> = scene.points.iter().flatten().copied().collect();
    let cameras = scene.cameras.supervision.clone();
    let images =
        scene.supervision.iter().map(|img| img.iter().map(|&b| b as f32 / 255.0).collect()).collect();
    TrainScene::new(gpu, cloud, cameras, images)
        .map_err(|e| DataError::Invalid(format!("{}: {e}", scene.dir.display())))
}
