//! The generators' config (video- and image-conditioned).

use serde::{Deserialize, Serialize};
use velox_engine::{Error, Result};

use super::{heads_ok, read_config_file};

/// What a generator is conditioned on: a 24-frame video, or one image (the first frame).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GenerationTask {
    Video,
    Image,
}

impl GenerationTask {
    /// Frames of the condition.
    pub fn frames(self) -> usize {
        match self {
            GenerationTask::Video => crate::velox::autoencoder::FRAMES,
            GenerationTask::Image => 1,
        }
    }
}

/// The generator (docs/models.md, Generation; paper Sec. 3 and supplement): a DiT over the
/// normalised dynamic tokens (patch size 1, learned zero-initialised positions), conditioned by
/// cross-attention on tokens of the video's frames (DINOv2 patch features ++ a learned linear
/// embedding of the RGB patch ++ Fourier(frame time)) and by adaLN on the flow time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeneratorConfig {
    pub name: String,
    pub task: GenerationTask,
    /// Width of the tokens it generates (the encoder's `token_dim`) and how many (`tokens`).
    pub token_dim: usize,
    pub tokens: usize,
    pub width: usize,
    pub heads: usize,
    pub blocks: usize,
    pub mlp_ratio: usize,
    /// Fourier frequencies of the flow time (log-spaced 2^0 .. 2^time_max_octave).
    pub time_freqs: usize,
    pub time_max_octave: f64,
    /// Side of the square frames the condition reads, in pixels (a multiple of 14: 532 in the
    /// paper, 38 x 38 patches).
    pub image_size: usize,
    /// Width of the DINOv2 patch features (1024 for ViT-L/14), or 0 to condition on the RGB
    /// patch embedding alone (no DINOv2 weights given).
    pub dino_width: usize,
    /// Width of the learned linear embedding of each 14 x 14 RGB patch.
    pub rgb_width: usize,
    /// Octaves of the frame time's Fourier embedding (with the time itself: 1 + 2 n values).
    pub frame_freqs: usize,
    /// Probability that a training sample sees no condition (classifier-free guidance).
    pub cond_dropout: f64,
    /// The flow time of training is uniform in [t_min, 1 - t_min].
    pub t_min: f32,
    pub batch: usize,
    pub peak_lr: f64,
    pub warmup: u64,
    pub max_grad_norm: f64,
    /// The autoencoder checkpoint whose tokens the generator learned (as for the voxel decoder).
    #[serde(default)]
    pub encoder_hash: Option<String>,
    /// The DINOv2 weight file the condition read, by hash: generation refuses another.
    #[serde(default)]
    pub dino_hash: Option<String>,
    /// The dataset's per-channel token mean and standard deviation (`velox encode`), by which
    /// the generator's tokens are normalised; set when training starts.
    #[serde(default)]
    pub token_mean: Vec<f32>,
    #[serde(default)]
    pub token_std: Vec<f32>,
}

impl GeneratorConfig {
    /// The paper's: 28 blocks of width 1152 and 16 heads, MLP ratio 4, 64 time frequencies,
    /// 532-pixel frames with DINOv2 ViT-L/14 features, 8192 tokens; 2065-wide condition tokens.
    pub fn paper() -> GeneratorConfig {
        GeneratorConfig {
            name: "paper".into(),
            task: GenerationTask::Video,
            token_dim: 32,
            tokens: 8192,
            width: 1152,
            heads: 16,
            blocks: 28,
            mlp_ratio: 4,
            time_freqs: 64,
            time_max_octave: 7.0,
            image_size: 532,
            dino_width: 1024,
            rgb_width: 1024,
            frame_freqs: 8,
            cond_dropout: 0.1,
            t_min: 1e-3,
            batch: 1,
            peak_lr: 1e-4,
            warmup: 4000,
            max_grad_norm: 1.0,
            encoder_hash: None,
            dino_hash: None,
            token_mean: Vec::new(),
            token_std: Vec::new(),
        }
    }

    /// A generator that learns a handful of procedural scenes on lavapipe: the small
    /// autoencoder's 256 tokens, 56-pixel frames (4 x 4 patches), no DINOv2.
    pub fn small() -> GeneratorConfig {
        GeneratorConfig {
            name: "small".into(),
            tokens: 256,
            width: 128,
            heads: 4,
            blocks: 4,
            time_freqs: 16,
            image_size: 56,
            dino_width: 0,
            rgb_width: 64,
            batch: 4,
            peak_lr: 1e-3,
            warmup: 100,
            ..GeneratorConfig::paper()
        }
    }

    /// The smallest generator that exercises every part: for tests.
    pub fn tiny() -> GeneratorConfig {
        GeneratorConfig {
            name: "tiny".into(),
            tokens: 24,
            token_dim: 8,
            width: 32,
            heads: 2,
            blocks: 2,
            mlp_ratio: 2,
            time_freqs: 4,
            image_size: 28,
            dino_width: 0,
            rgb_width: 16,
            frame_freqs: 2,
            batch: 2,
            peak_lr: 3e-3,
            warmup: 10,
            ..GeneratorConfig::paper()
        }
    }

    /// A config by name: `paper`, `small`, `tiny`, or a path to a JSON file.
    pub fn named(name: &str) -> Result<GeneratorConfig> {
        match name {
            "paper" => Ok(GeneratorConfig::paper()),
            "small" => Ok(GeneratorConfig::small()),
            "tiny" => Ok(GeneratorConfig::tiny()),
            path => read_config_file(path, GeneratorConfig::validate),
        }
    }

    /// Tokens (`[.., token_dim]` rows) into the generator's normalised space: `(x - mean) / std`
    /// per channel (identity where no statistics are set).
    pub fn normalise(&self, tokens: &[f32]) -> Vec<f32> {
        self.map_tokens(tokens, |v, m, s| (v - m) / s)
    }

    /// Tokens back from the generator's normalised space: `x std + mean` per channel.
    pub fn denormalise(&self, tokens: &[f32]) -> Vec<f32> {
        self.map_tokens(tokens, |v, m, s| v * s + m)
    }

    fn map_tokens(&self, tokens: &[f32], f: impl Fn(f32, f32, f32) -> f32) -> Vec<f32> {
        let (mean, std, d) = (&self.token_mean, &self.token_std, self.token_dim);
        if mean.is_empty() {
            return tokens.to_vec();
        }
        tokens.iter().enumerate().map(|(i, &v)| f(v, mean[i % d], std[i % d])).collect()
    }

    /// Width of a condition token: DINOv2 features ++ RGB embedding ++ Fourier(frame time).
    pub fn cond_width(&self) -> usize {
        self.dino_width + self.rgb_width + 1 + 2 * self.frame_freqs
    }

    /// Condition tokens of one scene: frames x patches.
    pub fn cond_tokens(&self) -> usize {
        let side = self.image_size / crate::velox::dinov2::PATCH;
        self.task.frames() * side * side
    }

    /// Checks that the sizes fit together, every number is in its range and the kernels exist.
    pub fn validate(&self) -> Result<()> {
        heads_ok("generator", self.width, self.heads)?;
        const WIDTH: usize = 8192;
        sizes!(self;
            token_dim: 1, WIDTH;
            tokens: 1, 1 << 20;
            width: 1, WIDTH;
            blocks: 1, 128;
            mlp_ratio: 1, 16;
            time_freqs: 1, 256;
            image_size: 14, 14 * 256;
            dino_width: 0, WIDTH;
            rgb_width: 1, WIDTH;
            frame_freqs: 0, 32;
            batch: 1, 4096;
        )?;
        if !self.image_size.is_multiple_of(crate::velox::dinov2::PATCH) {
            return Err(Error::Invalid(format!(
                "generator: image_size {} is not a multiple of the 14-pixel patch",
                self.image_size
            )));
        }
        numbers!(self;
            time_max_octave: 0.0, 30.0, true;
            cond_dropout: 0.0, 1.0, true;
            t_min: 0.0, 0.49, true;
            peak_lr: 0.0, 1.0, false;
            max_grad_norm: 0.0, 1e9, false;
        )?;
        let stats = [self.token_mean.len(), self.token_std.len()];
        if stats != [0, 0] && stats != [self.token_dim; 2] {
            return Err(Error::Invalid(format!(
                "generator: token statistics of {} and {} channels for {}-wide tokens",
                stats[0], stats[1], self.token_dim
            )));
        }
        if let Some(i) = self.token_std.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(Error::Invalid(format!(
                "generator: token_std[{i}] = {} is not positive",
                self.token_std[i]
            )));
        }
        Ok(())
    }
}
