//! A trained generator with the models it was trained against: the autoencoder whose tokens it
//! makes and DINOv2 where it reads image features, each checked against the hashes the
//! generator recorded, and the generation of tokens from condition frames.

use std::path::Path;

use velox_engine::{Error, Gpu, Result, Tensor};
use velox_models::velox::autoencoder::Autoencoder;
use velox_models::velox::dinov2::Dinov2;
use velox_models::velox::generator::{GenerateSpec, Generator};
use velox_models::Model;

use crate::GenScenes;

/// The generator, the autoencoder and DINOv2 (when the generator reads it), checked against
/// each other.
pub struct GeneratorModels {
    pub generator: Generator,
    pub ae: Autoencoder,
    pub dino: Option<Dinov2>,
}

impl GeneratorModels {
    /// Loads the three checkpoints; fails, naming the file and both hashes, where the
    /// autoencoder or DINOv2 is not the one the generator was trained against, and where
    /// DINOv2 is given to a generator that reads none or missing for one that does.
    pub fn load(
        gpu: &Gpu,
        generator: &Path,
        autoencoder: &Path,
        dinov2: Option<&Path>,
    ) -> Result<GeneratorModels> {
        let g = Generator::load(gpu, generator)?;
        g.check_encoder(autoencoder)?;
        let ae = Autoencoder::load(gpu, autoencoder)?;
        let dino = match (&g.cfg.dino_hash, dinov2) {
            (None, None) => None,
            (None, Some(_)) => {
                return Err(Error::setting(
                    "dinov2",
                    "the generator was trained without DINOv2: leave out {dinov2}",
                ))
            }
            (Some(_), None) => {
                return Err(Error::setting(
                    "dinov2",
                    "the generator was trained on DINOv2 features: give its weights as {dinov2}",
                ))
            }
            (Some(want), Some(path)) => {
                let d = Dinov2::load(gpu, path)?;
                let got = d.file_hash.as_deref().unwrap_or_default();
                if got != want {
                    return Err(Error::Invalid(format!(
                        "the generator was trained on DINOv2 weights of hash {want}; {} has hash {got}",
                        path.display()
                    )));
                }
                Some(d)
            }
        };
        Ok(GeneratorModels { generator: g, ae, dino })
    }

    /// The generator's tokens for condition frames `pixels`, in the autoencoder's space (the
    /// generator's normalisation undone); `step(i)` after each of the sampler's steps.
    pub fn generate(
        &self,
        gpu: &Gpu,
        pixels: &[f32],
        spec: &GenerateSpec,
        step: &mut dyn FnMut(usize),
    ) -> Result<Tensor> {
        let g = &self.generator;
        let condition = GenScenes::condition(gpu, &g.cfg, self.dino.as_ref(), pixels)?;
        let made = g.generate_with_progress(&condition, spec, step)?;
        let tokens = g.cfg.denormalise(&made.read::<f32>()?);
        Tensor::from_slice(gpu, made.shape(), &tokens)
    }
}
