//! What every trainable model of Velox is to the code that starts, loads and saves it: its
//! config by name or file, a fresh model of a config, the model a checkpoint holds and that
//! checkpoint's config. [`Model`] is the one way to load a model; the run API
//! (`velox_tasks::run`) starts every training run through it, and the command line and the
//! Python package load every checkpoint through it.
//!
//! Tests: `tests/training/train_primitives.rs` (save and load), `tools/tests/train_cli.rs`.

use std::path::Path;

use serde::de::DeserializeOwned;
use serde::Serialize;
use velox_engine::{Gpu, Result};

use crate::train::Trainable;

/// The names of the configs every model has (`docs/models.md`): the paper's sizes, a model
/// that trains in minutes, and one for tests. Any other name is a JSON config file.
pub const NAMED_CONFIGS: [&str; 3] = ["paper", "small", "tiny"];

/// Whether `name` is one of [`NAMED_CONFIGS`] (not a file).
pub fn is_named_config(name: &str) -> bool {
    NAMED_CONFIGS.contains(&name)
}

/// A model that trains, saves and loads.
pub trait Model: Trainable + Sized {
    /// Its sizes (`crate::config`), stored in each checkpoint.
    type Config: Clone + Serialize + DeserializeOwned;
    /// The kind its checkpoints record (`"velox autoencoder"`).
    const KIND: &'static str;
    /// What messages call it (`"autoencoder"`).
    const WHAT: &'static str;

    /// A config by name ([`NAMED_CONFIGS`]) or the path of a JSON file, validated.
    fn named_config(name: &str) -> Result<Self::Config>;

    /// A fresh model of `cfg`, its parameters drawn from `seed`.
    fn build(gpu: &Gpu, cfg: &Self::Config, seed: u64) -> Result<Self>;

    fn config(&self) -> &Self::Config;
    fn config_mut(&mut self) -> &mut Self::Config;
    /// The config's name (`"small"`, or what a config file calls itself).
    fn config_name(&self) -> &str;

    /// The config a checkpoint of this model holds (refused when it is another kind's).
    fn checkpoint_config(path: &Path) -> Result<Self::Config> {
        crate::checkpoint::model_config(path, Self::KIND, Self::WHAT)
    }

    /// The model a checkpoint holds, with its config, moments and step (or a weights file: its
    /// parameters and step; see [`crate::checkpoint::load_model`]).
    fn load(gpu: &Gpu, path: &Path) -> Result<Self> {
        let mut model = Self::build(gpu, &Self::checkpoint_config(path)?, 0)?;
        crate::checkpoint::load_model(path, model.store_mut())?;
        Ok(model)
    }

    /// Writes parameters, AdamW moments, the step and the config to `path` (atomically); a
    /// training run saves with its settings through `crate::train::trainer::save_checkpoint`.
    fn save(&self, path: &Path) -> Result<()> {
        crate::checkpoint::save(path, self.store(), &self.describe().to_string())
    }
}

/// [`Model`] for a Velox model: a struct with a field `cfg` of `$config` (which has `name` and
/// `named`), an inherent `new(gpu, cfg, seed)`, the module's `MODEL_KIND`, and [`Trainable`].
macro_rules! model {
    ($model:ty, $config:ty, $what:literal) => {
        impl $crate::model::Model for $model {
            type Config = $config;
            const KIND: &'static str = MODEL_KIND;
            const WHAT: &'static str = $what;

            fn named_config(name: &str) -> velox_engine::Result<$config> {
                <$config>::named(name)
            }

            fn build(gpu: &velox_engine::Gpu, cfg: &$config, seed: u64) -> velox_engine::Result<Self> {
                <$model>::new(gpu, cfg, seed)
            }

            fn config(&self) -> &$config {
                &self.cfg
            }

            fn config_mut(&mut self) -> &mut $config {
                &mut self.cfg
            }

            fn config_name(&self) -> &str {
                &self.cfg.name
            }
        }
    };
}
pub(crate) use model;
