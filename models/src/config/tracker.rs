//! The tracker's config.

use serde::{Deserialize, Serialize};
use velox_engine::Result;

use super::{heads_ok, read_config_file};

/// The loss of the tracker's predicted positions.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrackLoss {
    /// Mean absolute error per coordinate.
    L1,
    /// Mean squared error per coordinate.
    L2,
}

/// The 3D tracking network (a Perceiver IO): each query, a point on the first frame, Fourier
/// embedded, cross-attends to the tokens of the RGBD video's cloud in `blocks` blocks of
/// cross-attention and SwiGLU feed-forward (no attention among queries: each is tracked on
/// its own, so any number run in chunks), and a head gives its offset from the query at each
/// of the 24 frames.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrackerConfig {
    pub name: String,
    /// Width of the tokens it reads (the encoder's `token_dim`).
    pub token_dim: usize,
    pub width: usize,
    pub heads: usize,
    pub blocks: usize,
    pub ffn_ratio: usize,
    /// Octaves of the query's Fourier embedding (frequencies 1 to 2^(n - 1)).
    pub xyz_freqs: usize,
    /// 0: a linear input layer or head; else a GELU MLP through this width.
    pub input_hidden: usize,
    pub head_hidden: usize,
    pub loss: TrackLoss,
    /// The tokens' own query points (x, y, z, tau, Fourier embedded with `xyz_freqs`
    /// octaves) join the tokens as the cross-attention's context, so a query finds the
    /// tokens near it without reading their place out of the 32 numbers.
    #[serde(default)]
    pub token_positions: bool,
    /// Each query's colour on the first frame (its pixel of the video's frame 0, RGB in [0, 1])
    /// joins its feature beside its position, so a query can look for the tokens of its colour.
    #[serde(default)]
    pub query_colour: bool,
    /// Queries a scene contributes to a step, drawn at random from its tracks.
    pub queries_per_sample: usize,
    /// Scenes per micro-batch.
    pub batch: usize,
    pub peak_lr: f64,
    pub warmup: u64,
    pub max_grad_norm: f64,
    /// The hash of the autoencoder checkpoint whose tokens the tracker trained on (as for the
    /// voxel decoder): tracking with another autoencoder's tokens is refused.
    #[serde(default)]
    pub encoder_hash: Option<String>,
}

impl TrackerConfig {
    /// The paper's size: 8 blocks of width 768 (docs/models.md); a feed-forward ratio of 8 brings
    /// it to the paper's 123 M parameters.
    pub fn paper() -> TrackerConfig {
        TrackerConfig {
            name: "paper".into(),
            token_dim: 32,
            width: 768,
            heads: 12,
            blocks: 8,
            ffn_ratio: 8,
            xyz_freqs: 8,
            input_hidden: 0,
            head_hidden: 0,
            loss: TrackLoss::L1,
            token_positions: false,
            query_colour: false,
            queries_per_sample: 2048,
            batch: 1,
            peak_lr: 1e-4,
            warmup: 4000,
            max_grad_norm: 1.0,
            encoder_hash: None,
        }
    }

    /// A tracker that learns a few procedural scenes in an hour on lavapipe.
    pub fn small() -> TrackerConfig {
        TrackerConfig {
            name: "small".into(),
            width: 128,
            heads: 4,
            blocks: 3,
            ffn_ratio: 4,
            queries_per_sample: 512,
            peak_lr: 2e-3,
            warmup: 50,
            ..TrackerConfig::paper()
        }
    }

    /// The smallest tracker that exercises every part (MLP input and head included): for tests.
    pub fn tiny() -> TrackerConfig {
        TrackerConfig {
            name: "tiny".into(),
            width: 32,
            heads: 2,
            blocks: 2,
            ffn_ratio: 2,
            xyz_freqs: 4,
            input_hidden: 32,
            head_hidden: 32,
            queries_per_sample: 64,
            peak_lr: 5e-3,
            warmup: 10,
            ..TrackerConfig::paper()
        }
    }

    /// A config by name: `paper`, `small`, `tiny`, or a path to a JSON file.
    pub fn named(name: &str) -> Result<TrackerConfig> {
        match name {
            "paper" => Ok(TrackerConfig::paper()),
            "small" => Ok(TrackerConfig::small()),
            "tiny" => Ok(TrackerConfig::tiny()),
            path => read_config_file(path, TrackerConfig::validate),
        }
    }

    /// Checks that the sizes fit together, every number is in its range and the kernels exist.
    pub fn validate(&self) -> Result<()> {
        heads_ok("tracker", self.width, self.heads)?;
        const WIDTH: usize = 8192;
        sizes!(self;
            token_dim: 1, WIDTH;
            width: 1, WIDTH;
            blocks: 1, 64;
            ffn_ratio: 1, 16;
            xyz_freqs: 1, 32;
            input_hidden: 0, WIDTH * 16;
            head_hidden: 0, WIDTH * 16;
            queries_per_sample: 1, 1 << 20;
            batch: 1, 4096;
        )?;
        numbers!(self;
            peak_lr: 0.0, 1.0, false;
            max_grad_norm: 0.0, 1e9, false;
        )
    }
}
