//! Model sizes. Every number of docs/models.md is a field here, never a constant in code; `paper`
//! holds the paper's sizes, `small` a model that trains in minutes on one scene, `tiny` one
//! for tests. Configs are JSON (serde), stored in every checkpoint.

use serde::{Deserialize, Serialize};
use velox_engine::{Error, Result};

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
        let (e, s, g) = (&self.encoder, &self.surface, &self.gaussians);
        let sizes = [
            ("encoder.width", e.width, 1, WIDTH),
            ("encoder.tokens", e.tokens, 1, 1 << 20),
            ("encoder.token_dim", e.token_dim, 1, WIDTH),
            ("encoder.xyz_freqs", e.xyz_freqs, 1, FREQS),
            ("encoder.tau_freqs", e.tau_freqs, 1, FREQS),
            ("encoder.perceiver_blocks", e.perceiver_blocks, 1, BLOCKS),
            ("encoder.self_layers", e.self_layers, 0, BLOCKS),
            ("encoder.ffn_ratio", e.ffn_ratio, 1, RATIO),
            ("encoder.oversample", e.oversample, 1, 64),
            ("surface.width", s.width, 1, WIDTH),
            ("surface.blocks", s.blocks, 1, BLOCKS),
            ("surface.mlp_ratio", s.mlp_ratio, 1, RATIO),
            ("surface.xyz_freqs", s.xyz_freqs, 1, FREQS),
            ("surface.tau_freqs", s.tau_freqs, 1, FREQS),
            ("surface.time_freqs", s.time_freqs, 1, FREQS),
            ("surface.time_embed", s.time_embed, 1, WIDTH),
            ("surface.points_per_step", s.points_per_step, 1, POINTS),
            ("gaussians.width", g.width, 1, WIDTH),
            ("gaussians.blocks", g.blocks, 1, BLOCKS),
            ("gaussians.self_layers", g.self_layers, 0, BLOCKS),
            ("gaussians.ffn_ratio", g.ffn_ratio, 1, RATIO),
            ("gaussians.grid", g.grid, 1, 512),
            ("gaussians.gaussians_per_voxel", g.gaussians_per_voxel, 1, 1024),
            ("gaussians.xyz_freqs", g.xyz_freqs, 1, FREQS),
            ("gaussians.tau_freqs", g.tau_freqs, 1, FREQS),
            ("gaussians.window_voxels", g.window_voxels, 1, g.grid),
            ("gaussians.input_hidden", g.input_hidden, 0, WIDTH * RATIO),
            ("gaussians.head_hidden", g.head_hidden, 0, WIDTH * RATIO),
            ("batch", self.batch, 1, 4096),
            ("frames_per_sample", self.frames_per_sample, 1, 24),
            ("views_per_step", self.views_per_step, 1, 1024),
            ("encoder_points", self.encoder_points, 0, POINTS),
        ];
        check_sizes(&sizes)?;
        // (name, value, least, most, whether the least itself is allowed)
        let numbers = [
            ("encoder.xyz_max_octave", e.xyz_max_octave, -30.0, 30.0, true),
            ("encoder.tau_max_octave", e.tau_max_octave, -30.0, 30.0, true),
            ("encoder.time_scale", e.time_scale as f64, 0.0, 1e6, false),
            ("encoder.token_noise", e.token_noise as f64, 0.0, 1e3, true),
            ("encoder.token_reg", e.token_reg as f64, 0.0, 1e3, true),
            ("surface.xyz_max_octave", s.xyz_max_octave, -30.0, 30.0, true),
            ("surface.tau_max_octave", s.tau_max_octave, -30.0, 30.0, true),
            ("surface.time_max_octave", s.time_max_octave, -30.0, 30.0, true),
            ("surface.t_min", s.t_min as f64, 0.0, 0.499, true),
            ("gaussians.offset_range", g.offset_range as f64, 0.0, 1.0, true),
            ("gaussians.scale_min", g.scale_min as f64, 0.0, g.scale_max as f64, false),
            ("gaussians.scale_max", g.scale_max as f64, 0.0, 10.0, false),
            ("peak_lr", self.peak_lr, 0.0, 1.0, false),
            ("max_grad_norm", self.max_grad_norm, 0.0, 1e9, false),
        ];
        check_numbers(&numbers)
    }
}

/// Reads a config JSON file and validates it; errors name the file.
fn read_config_file<T: serde::de::DeserializeOwned>(path: &str, validate: fn(&T) -> Result<()>) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        Error::Invalid(format!(
            "config {path:?} is not paper, small or tiny, and cannot be read as a file: {e}"
        ))
    })?;
    let c: T = serde_json::from_str(&text).map_err(|e| Error::Invalid(format!("config file {path}: {e}")))?;
    validate(&c).map_err(|e| match e {
        Error::Invalid(why) => Error::Invalid(format!("config file {path}: {why}")),
        other => other,
    })?;
    Ok(c)
}

/// An attention layer of `width` splits into `heads` of a width the kernels are compiled for.
fn heads_ok(what: &str, width: usize, heads: usize) -> Result<()> {
    if heads == 0 || !width.is_multiple_of(heads) {
        return Err(Error::Invalid(format!("{what}: width {width} does not split into {heads} heads")));
    }
    let d = width / heads;
    if !velox_engine::ops::attention::HEAD_DIMS.contains(&d) {
        return Err(Error::Invalid(format!(
            "{what}: head width {d} has no attention kernel (compiled: {:?})",
            velox_engine::ops::attention::HEAD_DIMS
        )));
    }
    Ok(())
}

/// Every `(name, value, least, most)` size within its bounds.
fn check_sizes<S: AsRef<str>>(sizes: &[(S, usize, usize, usize)]) -> Result<()> {
    for (name, v, lo, hi) in sizes {
        let (name, v, lo, hi) = (name.as_ref(), *v, *lo, *hi);
        if !(lo..=hi).contains(&v) {
            return Err(Error::Invalid(format!("config: {name} is {v}, expected {lo} to {hi}")));
        }
    }
    Ok(())
}

/// Every `(name, value, least, most, whether the least itself is allowed)` number finite and
/// in its range.
fn check_numbers(numbers: &[(&str, f64, f64, f64, bool)]) -> Result<()> {
    for &(name, v, lo, hi, closed) in numbers {
        let above = if closed { v >= lo } else { v > lo };
        if !(v.is_finite() && above && v <= hi) {
            let open = if closed { "[" } else { "(" };
            return Err(Error::Invalid(format!(
                "config: {name} is {v}, expected a number in {open}{lo}, {hi}]"
            )));
        }
    }
    Ok(())
}

/// One stage of the voxel decoder: a Perceiver over coarse cells.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VoxelStageConfig {
    pub width: usize,
    pub heads: usize,
    pub blocks: usize,
    pub self_layers: usize,
    pub ffn_ratio: usize,
    /// Self-attention windows, in coarse cells per axis.
    pub window_cells: usize,
    /// 0: a linear input layer or head; else a GELU MLP through this width.
    pub input_hidden: usize,
    pub head_hidden: usize,
}

/// The loss of the voxel decoder's occupancy logits.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OccupancyLoss {
    /// Binary cross-entropy.
    Bce,
    /// The focal loss with this focusing gamma (at least 1).
    Focal { gamma: f32 },
}

fn default_cell_threshold() -> f32 {
    0.5
}

/// The voxel decoder: the occupied voxels of the 64^3 grid at a frame time, from the tokens.
/// A coarse stage predicts which of the `cells`^3 cells hold surface; a fine stage, over those
/// cells only, predicts each one's (64 / cells)^3 voxels.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VoxelConfig {
    pub name: String,
    /// Width of the tokens it reads (the encoder's `token_dim`).
    pub token_dim: usize,
    /// Coarse cells per axis: 64 must be a multiple.
    pub cells: usize,
    pub coarse: VoxelStageConfig,
    pub fine: VoxelStageConfig,
    pub xyz_freqs: usize,
    pub tau_freqs: usize,
    /// The fine stage's voxel head: each refined cell's feature (the fine trunk's output, this
    /// wide) plus an embedding of each voxel's offset in the cell (Fourier, `offset_freqs`
    /// octaves), through GELU to one logit per voxel.
    pub voxel_hidden: usize,
    pub offset_freqs: usize,
    /// The fine trunk also gives each cell its own direction per hidden unit of the voxel head,
    /// added as `m_c . o_v` (`o_v` the voxel's offset): a cell then places its own planes,
    /// where `b_v` alone is the same for every cell.
    #[serde(default)]
    pub cell_directions: bool,
    pub loss: OccupancyLoss,
    /// A voxel (fine stage) is occupied where its probability is above this.
    pub threshold: f32,
    /// The fine stage refines the cells whose probability (coarse stage) is above this: lower
    /// than `threshold`, as a cell missed loses all its voxels where one refined for nothing
    /// costs only its share of the fine stage.
    #[serde(default = "default_cell_threshold")]
    pub cell_threshold: f32,
    /// In training the fine stage sees the occupied cells and those within this many cells of
    /// one, so it also learns what an empty cell next to the surface holds.
    pub dilate: usize,
    /// Scenes per micro-batch, and frames of each per step.
    pub batch: usize,
    pub frames_per_sample: usize,
    pub peak_lr: f64,
    pub warmup: u64,
    pub max_grad_norm: f64,
    /// The hash (`velox_models::velox::tokens::checkpoint_hash`) of the autoencoder checkpoint
    /// whose tokens the decoder trained on, recorded by `velox train voxels`: decoding with
    /// another autoencoder's tokens is refused.
    #[serde(default)]
    pub encoder_hash: Option<String>,
}

impl VoxelConfig {
    /// The paper's size: about 65 M parameters (the paper: 65.0 M, for its TRELLIS-latent
    /// variant), nearly all of them in the fine stage.
    pub fn paper() -> VoxelConfig {
        VoxelConfig {
            name: "paper".into(),
            token_dim: 32,
            cells: 16,
            coarse: VoxelStageConfig {
                width: 256,
                heads: 4,
                blocks: 2,
                self_layers: 1,
                ffn_ratio: 4,
                window_cells: 4,
                input_hidden: 0,
                head_hidden: 0,
            },
            fine: VoxelStageConfig {
                width: 512,
                heads: 8,
                blocks: 5,
                self_layers: 2,
                ffn_ratio: 4,
                window_cells: 4,
                input_hidden: 0,
                head_hidden: 2048,
            },
            xyz_freqs: 16,
            tau_freqs: 8,
            voxel_hidden: 256,
            offset_freqs: 3,
            // One scene, 600 steps of the small config: IoU 0.242 against 0.215 without, fine
            // loss 0.070 against 0.133 (and still falling where the other had stalled).
            cell_directions: true,
            loss: OccupancyLoss::Bce,
            threshold: 0.5,
            cell_threshold: default_cell_threshold(),
            dilate: 1,
            batch: 1,
            frames_per_sample: 1,
            peak_lr: 4.9e-4,
            warmup: 4000,
            max_grad_norm: 1.0,
            encoder_hash: None,
        }
    }

    /// A decoder that learns a few procedural scenes in an hour on lavapipe.
    pub fn small() -> VoxelConfig {
        let stage = |width, blocks| VoxelStageConfig {
            width,
            heads: width / 16,
            blocks,
            self_layers: 1,
            ffn_ratio: 4,
            window_cells: 4,
            input_hidden: 0,
            head_hidden: 0,
        };
        VoxelConfig {
            name: "small".into(),
            coarse: stage(32, 1),
            fine: stage(64, 2),
            xyz_freqs: 6,
            tau_freqs: 4,
            voxel_hidden: 64,
            frames_per_sample: 2,
            // Measured on one scene, 100 steps: 5e-3 with 20 warmup steps reached a coarse loss
            // of 0.07 where 2e-3 with 50 stayed at the plateau of 0.12.
            peak_lr: 5e-3,
            warmup: 20,
            ..VoxelConfig::paper()
        }
    }

    /// The smallest decoder that exercises every part (MLP head and input included): for tests.
    pub fn tiny() -> VoxelConfig {
        let mut c = VoxelConfig::small();
        c.name = "tiny".into();
        c.coarse.width = 32;
        c.coarse.heads = 2;
        c.fine.width = 32;
        c.fine.heads = 2;
        c.fine.blocks = 1;
        c.fine.input_hidden = 32;
        c.fine.head_hidden = 64;
        c.voxel_hidden = 32;
        c.peak_lr = 5e-3;
        c.warmup = 10;
        c
    }

    /// A config by name: `paper`, `small`, `tiny`, or a path to a JSON file.
    pub fn named(name: &str) -> Result<VoxelConfig> {
        match name {
            "paper" => Ok(VoxelConfig::paper()),
            "small" => Ok(VoxelConfig::small()),
            "tiny" => Ok(VoxelConfig::tiny()),
            path => read_config_file(path, VoxelConfig::validate),
        }
    }

    /// Voxels per cell along an axis.
    pub fn cell_side(&self) -> usize {
        64 / self.cells
    }

    /// Checks that the sizes fit together, every number is in its range and the kernels exist.
    pub fn validate(&self) -> Result<()> {
        if self.cells == 0 || !64usize.is_multiple_of(self.cells) {
            return Err(Error::Invalid(format!("voxel decoder: cells {} must divide 64", self.cells)));
        }
        const WIDTH: usize = 8192;
        let mut sizes: Vec<(String, usize, usize, usize)> = [
            ("token_dim", self.token_dim, 1, WIDTH),
            ("cells", self.cells, 1, 64),
            ("xyz_freqs", self.xyz_freqs, 1, 256),
            ("tau_freqs", self.tau_freqs, 1, 256),
            ("voxel_hidden", self.voxel_hidden, 1, WIDTH),
            ("offset_freqs", self.offset_freqs, 0, 16),
            ("dilate", self.dilate, 0, 64),
            ("batch", self.batch, 1, 4096),
            ("frames_per_sample", self.frames_per_sample, 1, 24),
        ]
        .map(|(n, v, lo, hi)| (n.to_string(), v, lo, hi))
        .into();
        for (stage, c) in [("coarse", &self.coarse), ("fine", &self.fine)] {
            heads_ok(&format!("voxel decoder {stage} stage"), c.width, c.heads)?;
            let name = |f: &str| format!("{stage}.{f}");
            sizes.extend([
                (name("width"), c.width, 1, WIDTH),
                (name("blocks"), c.blocks, 1, 64),
                (name("self_layers"), c.self_layers, 0, 64),
                (name("ffn_ratio"), c.ffn_ratio, 1, 16),
                (name("window_cells"), c.window_cells, 1, self.cells),
                (name("input_hidden"), c.input_hidden, 0, WIDTH * 16),
                (name("head_hidden"), c.head_hidden, 0, WIDTH * 16),
            ]);
        }
        check_sizes(&sizes)?;
        let gamma = match self.loss {
            OccupancyLoss::Bce => 1.0,
            OccupancyLoss::Focal { gamma } => gamma as f64,
        };
        check_numbers(&[
            ("loss.gamma", gamma, 1.0, 16.0, true),
            ("threshold", self.threshold as f64, 0.0, 1.0, false),
            ("cell_threshold", self.cell_threshold as f64, 0.0, 1.0, false),
            ("peak_lr", self.peak_lr, 0.0, 1.0, false),
            ("max_grad_norm", self.max_grad_norm, 0.0, 1e9, false),
        ])
    }
}

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
        check_sizes(&[
            ("token_dim", self.token_dim, 1, WIDTH),
            ("width", self.width, 1, WIDTH),
            ("blocks", self.blocks, 1, 64),
            ("ffn_ratio", self.ffn_ratio, 1, 16),
            ("xyz_freqs", self.xyz_freqs, 1, 32),
            ("input_hidden", self.input_hidden, 0, WIDTH * 16),
            ("head_hidden", self.head_hidden, 0, WIDTH * 16),
            ("queries_per_sample", self.queries_per_sample, 1, 1 << 20),
            ("batch", self.batch, 1, 4096),
        ])?;
        check_numbers(&[
            ("peak_lr", self.peak_lr, 0.0, 1.0, false),
            ("max_grad_norm", self.max_grad_norm, 0.0, 1e9, false),
        ])
    }
}

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
        check_sizes(&[
            ("token_dim", self.token_dim, 1, WIDTH),
            ("tokens", self.tokens, 1, 1 << 20),
            ("width", self.width, 1, WIDTH),
            ("blocks", self.blocks, 1, 128),
            ("mlp_ratio", self.mlp_ratio, 1, 16),
            ("time_freqs", self.time_freqs, 1, 256),
            ("image_size", self.image_size, 14, 14 * 256),
            ("dino_width", self.dino_width, 0, WIDTH),
            ("rgb_width", self.rgb_width, 1, WIDTH),
            ("frame_freqs", self.frame_freqs, 0, 32),
            ("batch", self.batch, 1, 4096),
        ])?;
        if !self.image_size.is_multiple_of(crate::velox::dinov2::PATCH) {
            return Err(Error::Invalid(format!(
                "generator: image_size {} is not a multiple of the 14-pixel patch",
                self.image_size
            )));
        }
        check_numbers(&[
            ("time_max_octave", self.time_max_octave, 0.0, 30.0, true),
            ("cond_dropout", self.cond_dropout, 0.0, 1.0, true),
            ("t_min", self.t_min as f64, 0.0, 0.49, true),
            ("peak_lr", self.peak_lr, 0.0, 1.0, false),
            ("max_grad_norm", self.max_grad_norm, 0.0, 1e9, false),
        ])?;
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn named_configs_are_valid_and_round_trip_through_json() {
        for name in ["paper", "small", "tiny"] {
            let c = AutoencoderConfig::named(name).unwrap();
            c.validate().unwrap();
            let back: AutoencoderConfig = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
            assert_eq!(back, c);
        }
        assert!(AutoencoderConfig::named("/no/such/config.json")
            .unwrap_err()
            .to_string()
            .contains("paper, small or tiny"));
        let mut c = AutoencoderConfig::tiny();
        c.encoder.heads = 3;
        assert!(c.validate().is_err());
    }

    #[test]
    fn generator_configs_are_valid_and_bad_ones_are_named() {
        for name in ["paper", "small", "tiny"] {
            let c = GeneratorConfig::named(name).unwrap();
            c.validate().unwrap();
            let back: GeneratorConfig = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
            assert_eq!(back, c);
        }
        assert_eq!(GeneratorConfig::paper().cond_width(), 2065);
        assert_eq!(GeneratorConfig::paper().cond_tokens(), 34656);
        let bad = |f: fn(&mut GeneratorConfig)| {
            let mut c = GeneratorConfig::small();
            f(&mut c);
            c.validate().unwrap_err().to_string()
        };
        assert!(bad(|c| c.image_size = 50).contains("multiple of the 14-pixel patch"));
        assert!(bad(|c| c.heads = 3).contains("heads"));
        assert!(bad(|c| c.cond_dropout = 1.5).contains("cond_dropout"));
        assert!(bad(|c| c.token_mean = vec![0.0; 3]).contains("statistics"));
        let c = GeneratorConfig {
            token_dim: 2,
            token_mean: vec![1.0, -2.0],
            token_std: vec![2.0, 0.5],
            ..GeneratorConfig::tiny()
        };
        assert_eq!(c.normalise(&[3.0, -1.0, 1.0, -2.0]), vec![1.0, 2.0, 0.0, 0.0]);
        assert_eq!(c.denormalise(&[1.0, 2.0, 0.0, 0.0]), vec![3.0, -1.0, 1.0, -2.0]);
    }

    #[test]
    fn tracker_configs_are_valid_and_bad_ones_are_named() {
        for name in ["paper", "small", "tiny"] {
            let c = TrackerConfig::named(name).unwrap();
            c.validate().unwrap();
            let back: TrackerConfig = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
            assert_eq!(back, c);
        }
        let mut c = TrackerConfig::tiny();
        c.heads = 3;
        assert!(c.validate().unwrap_err().to_string().contains("heads"));
        let mut c = TrackerConfig::tiny();
        c.queries_per_sample = 0;
        assert!(c.validate().unwrap_err().to_string().contains("queries_per_sample"));
        let mut c = TrackerConfig::tiny();
        c.peak_lr = f64::NAN;
        assert!(c.validate().unwrap_err().to_string().contains("peak_lr"));
    }

    #[test]
    fn voxel_configs_are_valid_and_bad_ones_are_named() {
        for name in ["paper", "small", "tiny"] {
            let c = VoxelConfig::named(name).unwrap();
            c.validate().unwrap();
            let back: VoxelConfig = serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
            assert_eq!(back, c);
        }
        let mut c = VoxelConfig::tiny();
        c.cells = 12;
        assert!(c.validate().unwrap_err().to_string().contains("divide 64"));
        let mut c = VoxelConfig::tiny();
        c.fine.window_cells = 100;
        assert!(c.validate().unwrap_err().to_string().contains("fine.window_cells"));
        let mut c = VoxelConfig::tiny();
        c.loss = OccupancyLoss::Focal { gamma: 0.5 };
        assert!(c.validate().unwrap_err().to_string().contains("gamma"));
        c.loss = OccupancyLoss::Focal { gamma: 2.0 };
        c.threshold = f32::NAN;
        assert!(c.validate().unwrap_err().to_string().contains("threshold"));
    }
}
