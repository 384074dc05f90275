//! The voxel decoder's accuracy on held-out scenes, as `velox eval voxels` reports it: per
//! scene and evaluated frame, the predicted occupied set of the 64^3 grid against the truth
//! (the dataset's occupancy): accuracy over every voxel, precision, recall and IoU of the
//! occupied set, and how many coarse cells the fine stage refined. A scene's figures are the
//! means over its frames, the overall ones the means over scenes. Accuracy alone says little
//! (an empty prediction scores about 99 % on a sparse grid); IoU is the figure to read.

use serde::Serialize;
use velox_engine::{Result, Tensor};

use crate::velox::autoencoder::tau_of;
use crate::velox::voxels::{cell_labels, VoxelDecoder, FRAME_WORDS, GRID};

/// How a predicted occupied set compares with the true one.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct VoxelMetrics {
    pub accuracy: f64,
    pub precision: f64,
    pub recall: f64,
    pub iou: f64,
    pub true_voxels: f64,
    pub predicted_voxels: f64,
    pub refined_cells: f64,
    /// The fraction of the true cells (those holding an occupied voxel) that the fine stage
    /// refined: the most of the occupied voxels it could find (1 when no cell is true).
    pub cell_recall: f64,
}

impl VoxelMetrics {
    /// The metrics of one frame's predicted words against its true words, the fine stage
    /// having refined the cells `refined` of a `cells`^3 grid. Precision is 1 for an empty
    /// prediction and recall 1 for an empty truth (nothing claimed wrongly, nothing missed);
    /// IoU is 1 when both are empty.
    pub fn of(predicted: &[u64], truth: &[u64], refined: &[usize], cells: usize) -> VoxelMetrics {
        let count = |f: fn(u64, u64) -> u64| -> u64 {
            predicted.iter().zip(truth).map(|(&p, &t)| f(p, t).count_ones() as u64).sum()
        };
        let (tp, fp, fn_) = (count(|p, t| p & t), count(|p, t| p & !t), count(|p, t| !p & t));
        let all = (GRID * GRID * GRID) as f64;
        let ratio = |a: u64, b: u64| if b == 0 { 1.0 } else { a as f64 / b as f64 };
        VoxelMetrics {
            accuracy: (all - (fp + fn_) as f64) / all,
            precision: ratio(tp, tp + fp),
            recall: ratio(tp, tp + fn_),
            iou: ratio(tp, tp + fp + fn_),
            true_voxels: (tp + fn_) as f64,
            predicted_voxels: (tp + fp) as f64,
            refined_cells: refined.len() as f64,
            cell_recall: {
                let labels = cell_labels(truth, cells);
                let found = refined.iter().filter(|&&c| labels[c]).count();
                ratio(found as u64, labels.iter().filter(|&&l| l).count() as u64)
            },
        }
    }

    /// The mean of `all` (zeros for none).
    pub fn mean(all: &[VoxelMetrics]) -> VoxelMetrics {
        let n = all.len().max(1) as f64;
        let sum = |f: fn(&VoxelMetrics) -> f64| all.iter().map(f).sum::<f64>() / n;
        VoxelMetrics {
            accuracy: sum(|m| m.accuracy),
            precision: sum(|m| m.precision),
            recall: sum(|m| m.recall),
            iou: sum(|m| m.iou),
            true_voxels: sum(|m| m.true_voxels),
            predicted_voxels: sum(|m| m.predicted_voxels),
            refined_cells: sum(|m| m.refined_cells),
            cell_recall: sum(|m| m.cell_recall),
        }
    }
}

/// One evaluated frame.
#[derive(Clone, Debug, Serialize)]
pub struct FrameVoxels {
    pub frame: usize,
    pub metrics: VoxelMetrics,
    /// The predicted words (not serialised: the command draws them).
    #[serde(skip)]
    pub predicted: Vec<u64>,
}

/// One evaluated scene.
#[derive(Clone, Debug, Serialize)]
pub struct SceneVoxels {
    pub name: String,
    pub mean: VoxelMetrics,
    pub frames: Vec<FrameVoxels>,
}

/// Predicts frames `0, frame_step, ...` of a scene (its tokens and its true occupancy, every
/// frame's words one after another) in one batch of frames, and measures each.
pub fn evaluate_scene(
    decoder: &VoxelDecoder,
    name: &str,
    tokens: &Tensor,
    occupancy: &[u64],
    frame_step: usize,
) -> Result<SceneVoxels> {
    let frames: Vec<usize> = (0..occupancy.len() / FRAME_WORDS).step_by(frame_step.max(1)).collect();
    let taus: Vec<f32> = frames.iter().map(|&f| tau_of(f)).collect();
    let predictions = decoder.predict(tokens, &taus)?;
    let frames: Vec<FrameVoxels> = frames
        .iter()
        .zip(predictions)
        .map(|(&f, p)| {
            let truth = &occupancy[f * FRAME_WORDS..(f + 1) * FRAME_WORDS];
            FrameVoxels {
                frame: f,
                metrics: VoxelMetrics::of(&p.occupancy, truth, &p.refined, decoder.cfg.cells),
                predicted: p.occupancy,
            }
        })
        .collect();
    let mean = VoxelMetrics::mean(&frames.iter().map(|f| f.metrics).collect::<Vec<_>>());
    Ok(SceneVoxels { name: name.to_string(), mean, frames })
}

/// Predicted against true occupancy seen along the three axes, side by side (`[64, 192, 3]`
/// RGB in [0, 1]): along each ray, green where a voxel is both predicted and true, red where a
/// true voxel was missed, blue where a predicted one is false (the colours add); black where
/// the ray meets nothing.
pub fn projections(predicted: &[u64], truth: &[u64]) -> Vec<f32> {
    let bit = |w: &[u64], i: usize| w[i / 64] >> (i % 64) & 1 == 1;
    let mut img = vec![0f32; GRID * 3 * GRID * 3];
    for axis in 0..3 {
        for a in 0..GRID {
            for b in 0..GRID {
                let (mut tp, mut fn_, mut fp) = (false, false, false);
                for d in 0..GRID {
                    let (x, y, z) = match axis {
                        0 => (d, a, b),
                        1 => (a, d, b),
                        _ => (a, b, d),
                    };
                    let i = x + GRID * (y + GRID * z);
                    let (p, t) = (bit(predicted, i), bit(truth, i));
                    tp |= p && t;
                    fn_ |= t && !p;
                    fp |= p && !t;
                }
                // Image rows run down: the second coordinate upside down.
                let px = ((GRID - 1 - b) * GRID * 3 + axis * GRID + a) * 3;
                img[px] = if fn_ { 1.0 } else { 0.0 };
                img[px + 1] = if tp { 1.0 } else { 0.0 };
                img[px + 2] = if fp { 1.0 } else { 0.0 };
            }
        }
    }
    img
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_of_small_cases_worked_by_hand() {
        let mut truth = vec![0u64; FRAME_WORDS];
        let mut pred = vec![0u64; FRAME_WORDS];
        truth[0] = 0b1111; // 4 true voxels
        pred[0] = 0b0111_0000_0011; // 2 right, 3 wrong
                                    // The true voxels (x = 0..3) lie in cell 0 of a 16^3 grid, which was refined.
        let m = VoxelMetrics::of(&pred, &truth, &[0, 5, 9], 16);
        assert_eq!((m.true_voxels, m.predicted_voxels, m.refined_cells), (4.0, 5.0, 3.0));
        assert_eq!(m.cell_recall, 1.0);
        let mut two = truth.clone();
        two[0] |= 1 << 5; // x = 5: cell 1, not refined
        assert_eq!(VoxelMetrics::of(&pred, &two, &[0, 5, 9], 16).cell_recall, 0.5);
        assert!((m.precision - 2.0 / 5.0).abs() < 1e-12);
        assert!((m.recall - 2.0 / 4.0).abs() < 1e-12);
        assert!((m.iou - 2.0 / 7.0).abs() < 1e-12);
        assert!((m.accuracy - (262144.0 - 5.0) / 262144.0).abs() < 1e-12);
        let empty = VoxelMetrics::of(&vec![0; FRAME_WORDS], &vec![0; FRAME_WORDS], &[], 16);
        assert_eq!(
            (empty.precision, empty.recall, empty.iou, empty.accuracy, empty.cell_recall),
            (1.0, 1.0, 1.0, 1.0, 1.0)
        );
        let none = VoxelMetrics::of(&vec![0; FRAME_WORDS], &truth, &[], 16);
        assert_eq!((none.precision, none.recall, none.iou), (1.0, 0.0, 0.0));
        let img = projections(&pred, &truth);
        assert_eq!(img.len(), 64 * 192 * 3);
        assert!(img.contains(&1.0));
    }
}
