//! Scenes as the autoencoder trains on them: the cloud, the supervision cameras in the
//! rasteriser's form, and the supervision images as f32 RGB in [0, 1]; and a dataset folder as
//! the trainer's [`SampleSource`] of them.

use std::path::{Path, PathBuf};

use velox_engine::ops::raster::Camera;
use velox_engine::Gpu;
use velox_models::train::source::SampleSource;
use velox_models::velox::autoencoder::TrainScene;

use crate::format::{list_scenes, read_scene, Scene};
use crate::{DataError, DataResult};

/// A scene read into host memory, ready to upload: what the trainer's background thread
/// hands over.
pub struct HostScene {
    pub dir: PathBuf,
    /// Rows of (x, y, z, r, g, b, tau).
    pub cloud: Vec<f32>,
    pub cameras: Vec<Camera>,
    /// Frame-major then view, RGB in [0, 1].
    pub images: Vec<Vec<f32>>,
}

impl HostScene {
    /// The training form of a scene read with its images (`read_scene(dir, true)`).
    pub fn new(scene: &Scene) -> DataResult<HostScene> {
        if scene.supervision.is_empty() {
            return Err(DataError::Invalid(format!(
                "{}: the scene was read without its images; training needs them",
                scene.dir.display()
            )));
        }
        Ok(HostScene {
            dir: scene.dir.clone(),
            cloud: scene.points.iter().flatten().copied().collect(),
            cameras: scene.cameras.supervision.clone(),
            images: scene
                .supervision
                .iter()
                .map(|img| img.iter().map(|&b| b as f32 / 255.0).collect())
                .collect(),
        })
    }

    /// Checks the scene and uploads it; the error names its folder.
    pub fn upload(self, gpu: &Gpu) -> DataResult<TrainScene> {
        let dir = self.dir;
        TrainScene::new(gpu, self.cloud, self.cameras, self.images)
            .map_err(|e| DataError::Invalid(format!("{}: {e}", dir.display())))
    }
}

/// Uploads a scene read with its images (`read_scene(dir, true)`) for training.
pub fn train_scene(gpu: &Gpu, scene: &Scene) -> DataResult<TrainScene> {
    HostScene::new(scene)?.upload(gpu)
}

/// The scenes of a dataset folder (as `velox data` writes them), in name order, as samples
/// for the trainer and the evaluation: read with their images on the reading thread, uploaded
/// to `gpu` when prepared.
pub struct SceneFolders {
    gpu: Gpu,
    dirs: Vec<PathBuf>,
}

impl SceneFolders {
    /// The scenes under `root`; none is an error that says how to make some.
    pub fn open(gpu: &Gpu, root: &Path) -> DataResult<SceneFolders> {
        let dirs = list_scenes(root)?;
        if dirs.is_empty() {
            return Err(DataError::Invalid(format!(
                "{} holds no scenes (folders with a meta.json); make some with `velox data synth`",
                root.display()
            )));
        }
        Ok(SceneFolders { gpu: gpu.clone(), dirs })
    }

    /// Keeps the first `n` scenes.
    pub fn truncate(&mut self, n: usize) {
        self.dirs.truncate(n);
    }

    /// The scene folders, in name order.
    pub fn dirs(&self) -> &[PathBuf] {
        &self.dirs
    }
}

impl SampleSource for SceneFolders {
    type Raw = HostScene;
    type Sample = TrainScene;

    fn len(&self) -> usize {
        self.dirs.len()
    }

    fn name(&self, index: usize) -> String {
        self.dirs[index].file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
    }

    fn location(&self, index: usize) -> String {
        self.dirs[index].display().to_string()
    }

    fn read(&self, index: usize) -> velox_engine::Result<HostScene> {
        Ok(HostScene::new(&read_scene(&self.dirs[index], true)?)?)
    }

    fn prepare(&self, raw: HostScene) -> velox_engine::Result<TrainScene> {
        Ok(raw.upload(&self.gpu)?)
    }
}
