//! The autoencoder's config: the encoder, the surface decoder and the Gaussian decoder.

use serde::{Deserialize, Serialize};
use velox_engine::{Error, Result};

use super::{heads_ok, read_config_file};

/// The encoder E: colour point cloud over time -> k dynamic tokens of `token_dim`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EncoderConfig {
    pub width: usize,
    pub heads: usize,
    /// k: the number of queries, hence of dynamic tokens.
    pub tokens: usize,
    pub token_dim: usize,
    /// Fourier frequencies of xyz (log-spaced 2^0 .. 2^xyz_max_octave) and of tau.
    pub xyz_freqs: usize,
    pub xyz_max_octave: f64,
    pub tau_freqs: usize,
    pub tau_max_octave: f64,
    pub perceiver_blocks: usize,
    pub self_layers: usize,
    pub ffn_ratio: usize,
    /// Voxel window size in x, y, z and in tau (6 frames = 0.06).
    pub window: [f32; 4],
    /// Whether every second self-attention layer shifts its windows by half a cell.
    pub shift_windows: bool,
    /// Weight of tau in 4D distances (FPS, cells).
    pub time_scale: f32,
    /// FPS draws `oversample * tokens` random candidates.
    pub oversample: usize,
    /// Gaussian noise added to the tokens in training, and the weight of L_C = mean(s^2).
    pub token_noise: f32,
    pub token_reg: f32,
}

/// The 4D surface decoder V: a rectified-flow velocity network over points.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfaceConfig {
    pub width: usize,
    pub heads: usize,
    pub blocks: usize,
    pub mlp_ratio: usize,
    pub xyz_freqs: usize,
    pub xyz_max_octave: f64,
    pub tau_freqs: usize,
    pub tau_max_octave: f64,
    /// Fourier frequencies of the flow time t (log-spaced 2^0 .. 2^time_max_octave), and the
    /// width of its embedding MLP.
    pub time_freqs: usize,
    #[serde(default = "default_time_max_octave")]
    pub time_max_octave: f64,
    pub time_embed: usize,
    /// Points per training step, and the range of the flow time.
    pub points_per_step: usize,
    pub t_min: f32,
}

/// The flow time lies in [0, 1], like tau: the same octave range (configs written before the
/// field existed read this).
fn default_time_max_octave() -> f64 {
    7.0
}

/// The Gaussian decoder G: occupied voxels at a frame -> 3D Gaussians.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GaussianConfig {
    pub width: usize,
    pub heads: usize,
    pub blocks: usize,
    pub self_layers: usize,
    pub ffn_ratio: usize,
    /// Voxel grid resolution over [-1, 1]^3, and Gaussians per occupied voxel.
    pub grid: usize,
    pub gaussians_per_voxel: usize,
    pub xyz_freqs: usize,
    pub tau_freqs: usize,
    /// Voxel windows for the query self-attention, in voxels per axis.
    pub window_voxels: usize,
    pub offset_range: f32,
    pub scale_min: f32,
    pub scale_max: f32,
    /// The input layer: one linear layer (0), or a GELU MLP through this hidden width.
    #[serde(default)]
    pub input_hidden: usize,
    /// The head that "expands" each voxel token to its Gaussians: one linear layer (0), or a
    /// GELU MLP through this hidden width.
    #[serde(default)]
    pub head_hidden: usize,
}

/// The autoencoder: encoder, surface decoder, Gaussian decoder, and how they train.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AutoencoderConfig {
    pub name: String,
    pub encoder: EncoderConfig,
    pub surface: SurfaceConfig,
    pub gaussians: GaussianConfig,
    pub peak_lr: f64,
    pub warmup: u64,
    pub max_grad_norm: f64,
    /// Scenes in a micro-batch: the samples one pass of the networks trains on, as
    /// variable-length segments through the attention kernels. The batch of an optimiser step
    /// is this times `velox train --accumulate` times the number of processes.
    #[serde(default = "one")]
    pub batch: usize,
    /// Frames of each scene a training step uses: each gives the surface loss its points and
    /// the Gaussian decoder a frame to decode and render.
    #[serde(default = "one")]
    pub frames_per_sample: usize,
    /// Supervision views rendered and compared per frame in a training step: more image signal
    /// for one pass of the networks.
    #[serde(default = "one")]
    pub views_per_step: usize,
    /// Points of the cloud the encoder reads per training step: a fresh random subset each
    /// step (0: the whole cloud, the paper's setting). Encoding costs time in proportion to
    /// the points, and a subset of a dense cloud keeps its shape; evaluation encodes the
    /// whole cloud.
    #[serde(default)]
    pub encoder_points: usize,
}

/// One view per step: the paper's setting, and what configs written before the field read.
fn one() -> usize {
    1
}

impl AutoencoderConfig {
    /// The paper's sizes (docs/models.md).
    pub fn paper() -> AutoencoderConfig {
        AutoencoderConfig {
            name: "paper".into(),
            encoder: EncoderConfig {
                width: 512,
                heads: 16,
                tokens: 8192,
                token_dim: 32,
                xyz_freqs: 32,
                xyz_max_octave: 12.0,
                tau_freqs: 8,
                tau_max_octave: 7.0,
                perceiver_blocks: 2,
                self_layers: 6,
                ffn_ratio: 4,
                window: [0.5, 0.5, 0.5, 0.06],
                shift_windows: true,
                time_scale: 1.0,
                oversample: 4,
                token_noise: 0.001,
                token_reg: 1e-4,
            },
            surface: SurfaceConfig {
                width: 512,
                heads: 8,
                blocks: 3,
                mlp_ratio: 4,
                xyz_freqs: 32,
                xyz_max_octave: 12.0,
                tau_freqs: 8,
                tau_max_octave: 7.0,
                time_freqs: 32,
                time_max_octave: 7.0,
                time_embed: 64,
                points_per_step: 16384,
                t_min: 1e-3,
            },
            gaussians: GaussianConfig {
                width: 512,
                heads: 8,
                blocks: 6,
                self_layers: 2,
                ffn_ratio: 4,
                grid: 64,
                gaussians_per_voxel: 64,
                xyz_freqs: 16,
                tau_freqs: 8,
                window_voxels: 8,
                offset_range: 0.05,
                scale_min: 0.001,
                scale_max: 0.01,
                // The paper's head "expanded by an MLP" and a two-layer input: 75.8 M
                // parameters in the Gaussian decoder, the paper's count (73.1 M without).
                input_hidden: 512,
                head_hidden: 2048,
            },
            peak_lr: 4.9e-4,
            warmup: 4000,
            max_grad_norm: 1.0,
            batch: 1,
            frames_per_sample: 1,
            views_per_step: 1,
            encoder_points: 0,
        }
    }

    /// A model that overfits one scene in minutes, lavapipe included.
    pub fn small() -> AutoencoderConfig {
        let mut c = AutoencoderConfig::paper();
        c.name = "small".into();
        c.encoder = EncoderConfig {
            width: 64,
            heads: 4,
            tokens: 256,
            perceiver_blocks: 1,
            self_layers: 2,
            xyz_freqs: 8,
            xyz_max_octave: 6.0,
            tau_freqs: 4,
            tau_max_octave: 4.0,
            ..c.encoder
        };
        c.surface = SurfaceConfig {
            width: 64,
            heads: 4,
            blocks: 2,
            xyz_freqs: 8,
            xyz_max_octave: 6.0,
            tau_freqs: 4,
            tau_max_octave: 4.0,
            time_freqs: 8,
            time_embed: 32,
            points_per_step: 2048,
            ..c.surface
        };
        c.gaussians = GaussianConfig {
            width: 64,
            heads: 4,
            blocks: 2,
            self_layers: 1,
            grid: 32,
            gaussians_per_voxel: 8,
            xyz_freqs: 6,
            tau_freqs: 4,
            window_voxels: 8,
            offset_range: 0.05,
            scale_min: 0.002,
            scale_max: 0.03,
            input_hidden: 0,
            head_hidden: 0,
            ..c.gaussians
        };
        c.peak_lr = 2e-3;
        c.warmup = 50;
        c
    }

    /// The smallest model that exercises every part: for tests.
    pub fn tiny() -> AutoencoderConfig {
        let mut c = AutoencoderConfig::small();
        c.name = "tiny".into();
        c.encoder.width = 32;
        c.encoder.heads = 2;
        c.encoder.tokens = 32;
        c.encoder.token_dim = 8;
        c.encoder.perceiver_blocks = 2;
        c.encoder.self_layers = 2;
        c.surface.width = 32;
        c.surface.heads = 2;
        c.surface.blocks = 1;
        c.surface.points_per_step = 256;
        c.gaussians.width = 32;
        c.gaussians.heads = 2;
        c.gaussians.blocks = 1;
        c.gaussians.grid = 16;
        c.gaussians.gaussians_per_voxel = 4;
        // Voxels of 0.125 and images of tens of pixels: Gaussians of a pixel or more.
        c.gaussians.scale_min = 0.01;
        c.gaussians.scale_max = 0.1;
        c.gaussians.offset_range = 0.1;
        // Both MLPs, as in the paper config, so the tests run them.
        c.gaussians.input_hidden = 32;
        c.gaussians.head_hidden = 64;
        c.peak_lr = 5e-3;
        c.warmup = 10;
        c
    }

    /// A config by name: `paper`, `small`, `tiny`, or a path to a JSON file.
    pub fn named(name: &str) -> Result<AutoencoderConfig> {
        match name {
            "paper" => Ok(AutoencoderConfig::paper()),
            "small" => Ok(AutoencoderConfig::small()),
            "tiny" => Ok(AutoencoderConfig::tiny()),
            path => read_config_file(path, AutoencoderConfig::validate),
        }
    }

    /// Checks that the sizes fit together and that the kernels exist for them.
    pub fn validate(&self) -> Result<()> {
        heads_ok("encoder", self.encoder.width, self.encoder.heads)?;
        heads_ok("surface decoder", self.surface.width, self.surface.heads)?;
        heads_ok("gaussian decoder", self.gaussians.width, self.gaussians.heads)?;
        let e = &self.encoder;
        if e.tokens == 0 || e.token_dim == 0 || e.perceiver_blocks == 0 {
            return Err(Error::Invalid(
                "encoder: tokens, token_dim and perceiver_blocks must be positive".into(),
            ));
        }
        if e.window.iter().any(|w| !(w.is_finite() && *w > 0.0)) {
            return Err(Error::Invalid(format!("encoder: window sizes {:?} must be positive", e.window)));
        }
        if self.views_per_step == 0 {
            return Err(Error::Invalid("views_per_step must be at least 1".into()));
        }
        if !(self.peak_lr.is_finite() && self.peak_lr > 0.0) {
            return Err(Error::Invalid(format!("peak learning rate {} must be positive", self.peak_lr)));
        }
        self.check_limits()
    }

    /// Every size within its limits and every number finite and in its range: a config file
    /// is input, and a size of 10^18 or a NaN must be an error, not an allocation or a model
    /// that trains to NaN.
    fn check_limits(&self) -> Result<()> {
        const WIDTH: usize = 8192;
        const BLOCKS: usize = 64;
        const RATIO: usize = 16;
        const FREQS: usize = 256;
        const POINTS: usize = 1 << 24;
        let g = &self.gaussians;
        sizes!(self;
            encoder.width: 1, WIDTH;
            encoder.tokens: 1, 1 << 20;
            encoder.token_dim: 1, WIDTH;
            encoder.xyz_freqs: 1, FREQS;
            encoder.tau_freqs: 1, FREQS;
            encoder.perceiver_blocks: 1, BLOCKS;
            encoder.self_layers: 0, BLOCKS;
            encoder.ffn_ratio: 1, RATIO;
            encoder.oversample: 1, 64;
            surface.width: 1, WIDTH;
            surface.blocks: 1, BLOCKS;
            surface.mlp_ratio: 1, RATIO;
            surface.xyz_freqs: 1, FREQS;
            surface.tau_freqs: 1, FREQS;
            surface.time_freqs: 1, FREQS;
            surface.time_embed: 1, WIDTH;
            surface.points_per_step: 1, POINTS;
            gaussians.width: 1, WIDTH;
            gaussians.blocks: 1, BLOCKS;
            gaussians.self_layers: 0, BLOCKS;
            gaussians.ffn_ratio: 1, RATIO;
            gaussians.grid: 1, 512;
            gaussians.gaussians_per_voxel: 1, 1024;
            gaussians.xyz_freqs: 1, FREQS;
            gaussians.tau_freqs: 1, FREQS;
            gaussians.window_voxels: 1, g.grid;
            gaussians.input_hidden: 0, WIDTH * RATIO;
            gaussians.head_hidden: 0, WIDTH * RATIO;
            batch: 1, 4096;
            frames_per_sample: 1, 24;
            views_per_step: 1, 1024;
            encoder_points: 0, POINTS;
        )?;
        // (name, value, least, most, whether the least itself is allowed)
        numbers!(self;
            encoder.xyz_max_octave: -30.0, 30.0, true;
            encoder.tau_max_octave: -30.0, 30.0, true;
            encoder.time_scale: 0.0, 1e6, false;
            encoder.token_noise: 0.0, 1e3, true;
            encoder.token_reg: 0.0, 1e3, true;
            surface.xyz_max_octave: -30.0, 30.0, true;
            surface.tau_max_octave: -30.0, 30.0, true;
            surface.time_max_octave: -30.0, 30.0, true;
            surface.t_min: 0.0, 0.499, true;
            gaussians.offset_range: 0.0, 1.0, true;
            gaussians.scale_min: 0.0, g.scale_max as f64, false;
            gaussians.scale_max: 0.0, 10.0, false;
            peak_lr: 0.0, 1.0, false;
            max_grad_norm: 0.0, 1e9, false;
        )
    }
}
