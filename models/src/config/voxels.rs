//! The voxel decoder's config: a coarse and a fine stage.

use serde::{Deserialize, Serialize};
use velox_engine::{Error, Result};

use super::{check_numbers, heads_ok, read_config_file};

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
        for (stage, c) in [("coarse", &self.coarse), ("fine", &self.fine)] {
            heads_ok(&format!("voxel decoder {stage} stage"), c.width, c.heads)?;
        }
        sizes!(self;
            token_dim: 1, WIDTH;
            cells: 1, 64;
            xyz_freqs: 1, 256;
            tau_freqs: 1, 256;
            voxel_hidden: 1, WIDTH;
            offset_freqs: 0, 16;
            dilate: 0, 64;
            batch: 1, 4096;
            frames_per_sample: 1, 24;
            coarse.width: 1, WIDTH;
            coarse.blocks: 1, 64;
            coarse.self_layers: 0, 64;
            coarse.ffn_ratio: 1, 16;
            coarse.window_cells: 1, self.cells;
            coarse.input_hidden: 0, WIDTH * 16;
            coarse.head_hidden: 0, WIDTH * 16;
            fine.width: 1, WIDTH;
            fine.blocks: 1, 64;
            fine.self_layers: 0, 64;
            fine.ffn_ratio: 1, 16;
            fine.window_cells: 1, self.cells;
            fine.input_hidden: 0, WIDTH * 16;
            fine.head_hidden: 0, WIDTH * 16;
        )?;
        // The focal loss's gamma lives inside an enum: named by hand.
        if let OccupancyLoss::Focal { gamma } = self.loss {
            check_numbers(&[("loss.gamma", gamma as f64, 1.0, 16.0, true)])?;
        }
        numbers!(self;
            threshold: 0.0, 1.0, false;
            cell_threshold: 0.0, 1.0, false;
            peak_lr: 0.0, 1.0, false;
            max_grad_norm: 0.0, 1e9, false;
        )
    }
}
