//! The voxel decoder (paper: section 3.3; the occupied voxels of a frame predicted from the
//! dynamic tokens, so Gaussians decode without sampling the surface ODE).

use velox_engine::{Error, Result, Tensor};

/// Side of the occupancy grid over [-1, 1]^3 the data stores and the decoder predicts.
pub const GRID: usize = 64;
/// 64-bit words of one frame's occupancy: voxel (x, y, z) is bit `i % 64` of word `i / 64`,
/// `i = x + 64 (y + 64 z)` (the dataset's `occupancy.bin` layout).
pub const FRAME_WORDS: usize = GRID * GRID * GRID / 64;

/// What the voxel decoder trains on from one scene: its stored tokens and its occupancy.
pub struct VoxelSample {
    /// The scene's tokens `[k, token_dim]` on the device (the frozen encoder's, from `velox
    /// encode`).
    pub tokens: Tensor,
    /// [`FRAME_WORDS`] words per frame, every frame of the clip.
    pub occupancy: Vec<u64>,
}

impl VoxelSample {
    /// Checks the shapes: tokens `[k > 0, d > 0]` f32, whole frames of occupancy.
    pub fn new(tokens: Tensor, occupancy: Vec<u64>) -> Result<VoxelSample> {
        let ok_tokens = matches!(tokens.shape(), [k, d] if *k > 0 && *d > 0)
            && tokens.dtype() == velox_engine::DType::F32;
        if !ok_tokens {
            return Err(Error::Shape(format!("voxel sample: tokens must be f32 [k, d], got {tokens:?}")));
        }
        if occupancy.is_empty() || !occupancy.len().is_multiple_of(FRAME_WORDS) {
            return Err(Error::Shape(format!(
                "voxel sample: {} occupancy words are not whole frames of {FRAME_WORDS}",
                occupancy.len()
            )));
        }
        Ok(VoxelSample { tokens, occupancy })
    }

    /// Frames of occupancy.
    pub fn frames(&self) -> usize {
        self.occupancy.len() / FRAME_WORDS
    }

    /// Whether voxel `(x, y, z)` is occupied at frame `f`.
    pub fn occupied(&self, f: usize, x: usize, y: usize, z: usize) -> bool {
        let i = x + GRID * (y + GRID * z);
        self.occupancy[f * FRAME_WORDS + i / 64] >> (i % 64) & 1 == 1
    }
}
