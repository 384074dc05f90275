//! The voxel decoder at the tiny config: its grid helpers against plain loops, its backward
//! pass against finite differences per tensor, a batch against its samples alone, that both
//! stages learn one frame beyond the label prior, that each scene is decoded from its own
//! tokens, and the paper config's parameter count.

use crate::common;
use common::*;
use velox::data::format::write_scene;
use velox::data::{procedural, read_scene, SynthOptions};
use velox::models::config::{OccupancyLoss, VoxelConfig};
use velox::models::velox::gaussians::occupied_voxels;
use velox::models::velox::voxels::{
    cell_labels, dilate, occupied_centres, voxel_of, VoxelDecoder, VoxelSample, FRAME_WORDS, GRID,
};

/// The occupancy of procedural scene `seed` (24 frames of 64^3 bits).
fn occupancy(gpu: &Gpu, seed: u64, test: &str) -> (Vec<u64>, Vec<[f32; 7]>) {
    let dir = std::env::temp_dir().join(format!("velox-voxels-{}-{test}-{seed}", std::process::id()));
    let (_, mesh) = procedural::scene(seed, None).unwrap();
    let opts = SynthOptions { res: 48, points: 20000, supersample: 1, tracks: 0, ..Default::default() };
    write_scene(gpu, &mesh, "test", None, seed, &opts, &dir, &mut |_| {}).unwrap();
    let s = read_scene(&dir, false).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    (s.occupancy, s.points)
}

/// `frames` frames of a ball of `radius` voxels whose centre (in voxels) moves from `from` to
/// `to` over the clip: a small occupancy, cheap for the fine stage.
fn ball(frames: usize, from: [f32; 3], to: [f32; 3], radius: f32) -> Vec<u64> {
    let mut words = vec![0u64; frames * FRAME_WORDS];
    for f in 0..frames {
        let s = f as f32 / 23.0;
        let c: [f32; 3] = std::array::from_fn(|k| from[k] + s * (to[k] - from[k]));
        for z in 0..GRID {
            for y in 0..GRID {
                for x in 0..GRID {
                    let d2 =
                        [x, y, z].iter().zip(&c).map(|(&v, &c)| (v as f32 + 0.5 - c).powi(2)).sum::<f32>();
                    if d2 <= radius * radius {
                        let i = x + GRID * (y + GRID * z);
                        words[f * FRAME_WORDS + i / 64] |= 1 << (i % 64);
                    }
                }
            }
        }
    }
    words
}

fn sample(gpu: &Gpu, seed: u64, occupancy: &[u64]) -> VoxelSample {
    let tokens = Rng::new(seed).normal_vec(48 * 32);
    VoxelSample::new(Tensor::from_slice(gpu, &[48, 32], &tokens).unwrap(), occupancy.to_vec()).unwrap()
}

fn zero(gpu: &Gpu, d: &VoxelDecoder) {
    let mut rec = gpu.recorder().unwrap();
    d.store.zero_grads(&mut rec).unwrap();
    rec.submit().unwrap();
}

#[test]
fn grid_helpers_match_plain_loops() {
    let mut rng = Rng::new(1);
    let mut words = vec![0u64; FRAME_WORDS];
    let mut on = Vec::new();
    for _ in 0..300 {
        let i = rng.below((GRID * GRID * GRID) as u32) as usize;
        words[i / 64] |= 1 << (i % 64);
        on.push(i);
    }
    for cells in [16, 8] {
        let s = GRID / cells;
        let labels = cell_labels(&words, cells);
        let mut want = vec![false; cells.pow(3)];
        for &i in &on {
            let (x, y, z) = (i % GRID, i / GRID % GRID, i / (GRID * GRID));
            want[x / s + cells * (y / s + cells * (z / s))] = true;
        }
        assert_eq!(labels, want, "cells {cells}");
        // Dilation by 1: a cell is on where a labelled cell is within one in every axis.
        let grown = dilate(&labels, cells, 1);
        for (c, &on) in grown.iter().enumerate() {
            let (i, j, l) = (c % cells, c / cells % cells, c / (cells * cells));
            let near = (0..cells.pow(3)).any(|o| {
                let (a, b, d) = (o % cells, o / cells % cells, o / (cells * cells));
                labels[o] && a.abs_diff(i) <= 1 && b.abs_diff(j) <= 1 && d.abs_diff(l) <= 1
            });
            assert_eq!(on, near, "cells {cells}, cell {c}");
        }
    }
    // Occupied centres at the full grid and at 32, against occupied_voxels of the same points.
    let points: Vec<f32> = on
        .iter()
        .flat_map(|&i| {
            let c = |v: usize| -1.0 + (v as f32 + 0.5) * 2.0 / GRID as f32;
            [c(i % GRID), c(i / GRID % GRID), c(i / (GRID * GRID)), 0.5, 0.5, 0.5, 0.0]
        })
        .collect();
    for grid in [64, 32] {
        assert_eq!(
            occupied_centres(&words, grid).unwrap(),
            occupied_voxels(&points, 0.0, grid),
            "grid {grid}"
        );
    }
    assert!(occupied_centres(&words, 48).is_err());
}

/// The step's gradient against central differences of its loss, along directions over every
/// parameter and over each tensor alone, with the parameters randomised (the default head
/// starts at std 0.01, which would shrink every gradient upstream of it). Would catch any
/// tensor's gradient wired wrong, either stage's, the token cross-attention's included.
#[test]
fn backward_matches_central_differences_per_tensor() {
    let gpu = gpu();
    let occ = ball(24, [20.0, 30.0, 34.0], [40.0, 34.0, 30.0], 6.0);
    // Each tensor alone in the case that has them all (cell directions); the others along
    // directions over every parameter and over each stage.
    let cases = [
        (OccupancyLoss::Bce, true, true),
        (OccupancyLoss::Bce, false, false),
        (OccupancyLoss::Focal { gamma: 2.0 }, false, false),
    ];
    for (loss, cell_directions, each) in cases {
        // The case checked per tensor at a coarser grid of cells and on one frame, to keep
        // its hundred-odd steps short.
        let (cells, frames_per_sample) = if each { (8, 1) } else { (16, 2) };
        let cfg = VoxelConfig { loss, cell_directions, cells, frames_per_sample, ..VoxelConfig::tiny() };
        let mut d = VoxelDecoder::new(&gpu, &cfg, 2).unwrap();
        randomize_params(&d.store, 13, 0.6);
        let s = sample(&gpu, 4, &occ);
        zero(&gpu, &d);
        let l0 = d.accumulate(&[&s], &mut [Rng::new(9)], 1.0).unwrap();
        assert_eq!(l0.terms.iter().map(|t| t.0).collect::<Vec<_>>(), ["total", "coarse", "fine"]);
        assert!(l0.terms.iter().all(|t| t.1 > 0.0), "{l0:?}");
        let grad: Vec<f32> = d.store.flat_grads().read().unwrap();
        let theta: Vec<f32> = d.store.flat_params().read().unwrap();
        let parts: Vec<ParamGroup> =
            ["", "coarse.", "fine.", "voxel_head."].iter().map(|p| ParamGroup::under(&d.store, p)).collect();
        let each = if each { ParamGroup::each(&d.store) } else { Vec::new() };
        let what = format!("{loss:?}, cell directions {cell_directions}");
        let mut at = |p: &[f32]| {
            d.store.flat_params().write(p).unwrap();
            d.accumulate(&[&s], &mut [Rng::new(9)], 1.0).unwrap().total()
        };
        // A step of 1e-3 over a whole part (2e-3 of the parameters' size); a tensor alone
        // takes 1e-2, where the loss's f32 rounding (about 1e-7) would swamp the small ones.
        let mut rng = Rng::new(5);
        let parts =
            check_directional(&what, &theta, &grad, &parts, (1, 1), 1e-3, (1e-2, 1e-4), &mut rng, &mut at);
        let each =
            check_directional(&what, &theta, &grad, &each, (1, 1), 1e-2, (1e-2, 1e-5), &mut rng, &mut at);
        if verbose() {
            eprintln!("{what}: worst relative error {parts:.2e} (parts), {each:.2e} (each tensor)");
        }
    }
}

#[test]
fn a_batch_gives_the_mean_of_its_samples_gradients() {
    let gpu = gpu();
    let (a, _) = occupancy(&gpu, 3, "batch");
    let (b, _) = occupancy(&gpu, 8, "batch");
    let cfg = VoxelConfig { frames_per_sample: 2, ..VoxelConfig::tiny() };
    let mut d = VoxelDecoder::new(&gpu, &cfg, 1).unwrap();
    let samples = [sample(&gpu, 1, &a), sample(&gpu, 2, &b), sample(&gpu, 3, &a)];
    let refs: Vec<&VoxelSample> = samples.iter().collect();
    let rngs = || (0..3).map(|i| Rng::new(20 + i)).collect::<Vec<_>>();
    zero(&gpu, &d);
    let batch = d.accumulate(&refs, &mut rngs(), 1.0 / 3.0).unwrap();
    let batch_grads: Vec<f32> = d.store.flat_grads().read().unwrap();
    zero(&gpu, &d);
    let mut total = 0.0;
    for (s, mut r) in refs.iter().zip(rngs()) {
        total += d.accumulate(&[s], std::slice::from_mut(&mut r), 1.0 / 3.0).unwrap().total();
    }
    let single_grads: Vec<f32> = d.store.flat_grads().read().unwrap();
    assert_nmse(
        "batch-3 gradient against three batch-1 gradients",
        &batch_grads,
        &f64s(&single_grads),
        1e-10,
    );
    assert!((batch.total() - total).abs() <= 1e-6 * total, "batch {} against singles {total}", batch.total());
}

/// The loss of the best constant logit (the label prior) over labels of which `positives` of
/// `total` are 1: what a decoder that learned only the occupancy rate scores.
fn prior_loss(kind: velox::engine::ops::loss::LossKind, positives: usize, total: usize) -> f64 {
    let at = |c: f64| {
        let f = |t: f64| velox::engine::ops::loss::reference::pointwise(kind, c, t).0;
        (positives as f64 * f(1.0) + (total - positives) as f64 * f(0.0)) / total as f64
    };
    (-20_000..=20_000).map(|i| at(i as f64 * 1e-3)).fold(f64::INFINITY, f64::min)
}

const LEARN_STEPS: u64 = 120;

/// One frame of one scene, its coarse cells and its voxels: both losses fall well below the
/// label prior's (the best constant logit for each stage's labels, computed here), which
/// already scores about half the starting focal loss. Would catch a stage that learns only
/// the occupancy rate.
#[test]
fn both_stages_learn_one_frame() {
    use velox::engine::ops::loss::LossKind;
    use velox::models::train::Trainable;
    let gpu = gpu();
    let (occ, _) = occupancy(&gpu, 3, "learn");
    let cfg = VoxelConfig { loss: OccupancyLoss::Focal { gamma: 2.0 }, ..VoxelConfig::tiny() };
    let mut d = VoxelDecoder::new(&gpu, &cfg, 1).unwrap();
    let s = sample(&gpu, 7, &occ[..FRAME_WORDS]);
    let mut history = Vec::new();
    for step in 1..=LEARN_STEPS {
        zero(&gpu, &d);
        let l = d.accumulate(&[&s], &mut [Rng::new(step)], 1.0).unwrap();
        history.push((l.terms[1].1, l.terms[2].1));
        let (lr, adamw) = (d.optimisation().learning_rate(step), d.adamw);
        let mut rec = gpu.recorder().unwrap();
        d.store.adamw_step(&mut rec, &adamw, lr, Some(1.0)).unwrap();
        rec.submit().unwrap();
    }
    // The labels each stage trains on: every cell, and the voxels of the dilated cells.
    let words = &occ[..FRAME_WORDS];
    let labels = cell_labels(words, cfg.cells);
    let chosen = dilate(&labels, cfg.cells, cfg.dilate);
    let per_cell = cfg.cell_side().pow(3);
    let fine: Vec<bool> = (0..labels.len())
        .filter(|&c| chosen[c])
        .flat_map(|c| (0..per_cell).map(move |v| voxel_of(c, v, cfg.cells)))
        .map(|i| words[i / 64] >> (i % 64) & 1 == 1)
        .collect();
    let kind = LossKind::Focal { gamma: 2.0 };
    let coarse_prior = prior_loss(kind, labels.iter().filter(|&&l| l).count(), labels.len());
    let fine_prior = prior_loss(kind, fine.iter().filter(|&&l| l).count(), fine.len());
    let mean = |r: &[(f64, f64)], f: fn(&(f64, f64)) -> f64| r.iter().map(f).sum::<f64>() / r.len() as f64;
    let (first, last) = (&history[..5], &history[history.len() - 5..]);
    let (c0, c1) = (mean(first, |h| h.0), mean(last, |h| h.0));
    let (f0, f1) = (mean(first, |h| h.1), mean(last, |h| h.1));
    if verbose() {
        eprintln!(
            "tiny voxel decoder, one frame, {LEARN_STEPS} steps: coarse {c0:.4} -> {c1:.4} (label prior {coarse_prior:.4}), \
             fine {f0:.4} -> {f1:.4} (label prior {fine_prior:.4})"
        );
    }
    // Measured on lavapipe: coarse 0.141 -> 0.0039 (prior 0.054), fine 0.201 -> 0.035 (prior
    // 0.065); after 50 steps the fine stage was still at 0.82 of its prior.
    assert!(c1 < 0.2 * coarse_prior, "coarse loss {c0} -> {c1}, the label prior's {coarse_prior}");
    assert!(f1 < 0.7 * fine_prior, "fine loss {f0} -> {f1}, the label prior's {fine_prior}");
}

/// The mean binary cross-entropy of `labels` under `logits` (0/1 labels).
fn cross_entropy(logits: &[f32], labels: impl Iterator<Item = bool>) -> f64 {
    let kind = velox::engine::ops::loss::LossKind::BceWithLogits;
    let (mut total, mut n) = (0.0, 0);
    for (&l, t) in logits.iter().zip(labels) {
        total += velox::engine::ops::loss::reference::pointwise(kind, l as f64, t as u8 as f64).0;
        n += 1;
    }
    total / n as f64
}

/// The cross-entropy of a scene's occupancy at `frame` under the decoder's logits from
/// `tokens`: (coarse cells, fine voxels of `cells`).
fn surprise(
    d: &VoxelDecoder,
    tokens: &Tensor,
    truth: &VoxelSample,
    frame: usize,
    cells: &[usize],
) -> (f64, f64) {
    let gpu = tokens.gpu();
    let tau = frame as f32 / 100.0;
    let words = &truth.occupancy[frame * FRAME_WORDS..(frame + 1) * FRAME_WORDS];
    let mut rec = gpu.recorder().unwrap();
    let coarse = d.coarse_logits(&mut rec, tokens, &[tau]).unwrap();
    let fine = d.fine_logits(&mut rec, tokens, &[tau], &[cells.to_vec()]).unwrap().unwrap();
    rec.submit().unwrap();
    let n = d.cfg.cells;
    let per_cell = d.cfg.cell_side().pow(3);
    let coarse = cross_entropy(&coarse.read::<f32>().unwrap(), cell_labels(words, n).into_iter());
    let voxels = cells.iter().flat_map(|&c| (0..per_cell).map(move |v| voxel_of(c, v, n)));
    let fine =
        cross_entropy(&fine.read::<f32>().unwrap(), voxels.map(|i| words[i / 64] >> (i % 64) & 1 == 1));
    (coarse, fine)
}

/// Two scenes whose balls move along different paths, with tokens of their own: only the
/// tokens tell them apart. Trained on both, the decoder's logits from a scene's own tokens
/// make its own truth far more likely than the other's (cross-entropy per cell, and per voxel
/// of the cells the truth fills), and the other scene's tokens or zero tokens make it
/// clearly less likely. Would catch a decoder that does not read its tokens (the
/// cross-attention's output zeroed, its token path unlearned), in either stage.
#[test]
fn each_scene_is_decoded_from_its_own_tokens() {
    let gpu = gpu();
    let balls = [
        ball(24, [18.0, 22.0, 30.0], [22.0, 26.0, 34.0], 11.0),
        ball(24, [46.0, 42.0, 34.0], [42.0, 38.0, 30.0], 11.0),
    ];
    let scenes = [sample(&gpu, 100, &balls[0]), sample(&gpu, 200, &balls[1])];
    let cfg = VoxelConfig { frames_per_sample: 1, cells: 8, dilate: 0, ..VoxelConfig::tiny() };
    let mut d = VoxelDecoder::new(&gpu, &cfg, 1).unwrap();
    trainer_losses(&mut d, &[&scenes[0], &scenes[1]], STEPS, Precision::F32);
    let zeros = Tensor::from_slice(&gpu, &[48, 32], &vec![0f32; 48 * 32]).unwrap();
    let frame = 11;
    // The cells each ball fills at that frame: the fine stage is judged on a scene's own.
    let n = cfg.cells;
    let cells: Vec<Vec<usize>> = scenes
        .iter()
        .map(|s| {
            let labels = cell_labels(&s.occupancy[frame * FRAME_WORDS..(frame + 1) * FRAME_WORDS], n);
            (0..n.pow(3)).filter(|&c| labels[c]).collect()
        })
        .collect();
    for (i, s) in scenes.iter().enumerate() {
        let other = &scenes[1 - i];
        let own = surprise(&d, &s.tokens, s, frame, &cells[i]);
        let to_other = surprise(&d, &s.tokens, other, frame, &cells[1 - i]);
        let swapped = surprise(&d, &other.tokens, s, frame, &cells[i]);
        let zeroed = surprise(&d, &zeros, s, frame, &cells[i]);
        if verbose() {
            eprintln!(
                "scene {i}: cross-entropy (cells, voxels) of its truth {own:.3?}, of the other's {to_other:.3?}; \
                 from the other's tokens {swapped:.3?}, from zero tokens {zeroed:.3?}"
            );
        }
        for (what, a, b) in [
            ("cells", own.0, [to_other.0, swapped.0, zeroed.0]),
            ("voxels", own.1, [to_other.1, swapped.1, zeroed.1]),
        ] {
            assert!(
                b.iter().all(|&b| b > 3.0 * a),
                "scene {i}, {what}: {a} for its own truth from its tokens, {b:?}"
            );
        }
    }
}

const STEPS: u64 = 150;

#[test]
fn the_paper_config_counts_about_65_million_parameters() {
    let m = VoxelDecoder::declare(&gpu(), &VoxelConfig::paper()).unwrap().num_parameters() as f64 / 1e6;
    assert!((m - 65.0).abs() < 0.05 * 65.0, "{m:.2} M");
}

#[test]
fn frames_decode_together_as_alone() {
    // Frames share no window: the logits of a frame among others are its logits alone, and
    // predictions of several frames at once are each frame's own.
    let gpu = gpu();
    let (occ, _) = occupancy(&gpu, 3, "frames");
    let d = VoxelDecoder::new(&gpu, &VoxelConfig::tiny(), 5).unwrap();
    let s = sample(&gpu, 4, &occ);
    let taus = [0.0, 0.07, 0.15];
    let n = VoxelConfig::tiny().cells.pow(3);
    let mut rec = gpu.recorder().unwrap();
    let together = d.coarse_logits(&mut rec, &s.tokens, &taus).unwrap();
    let alone: Vec<Tensor> =
        taus.iter().map(|&t| d.coarse_logits(&mut rec, &s.tokens, &[t]).unwrap()).collect();
    rec.submit().unwrap();
    let together: Vec<f32> = together.read().unwrap();
    for (f, a) in alone.iter().enumerate() {
        let a: Vec<f32> = a.read().unwrap();
        assert_nmse(&format!("frame {f} among three"), &together[f * n..(f + 1) * n], &f64s(&a), 1e-10);
    }
    // Frames differ (tau reaches the queries).
    assert_ne!(&together[..n], &together[n..2 * n]);
}

/// Would catch: a voxel decoder step recorded while the last runs that differs from one
/// recorded after it.
#[test]
fn steps_recorded_ahead_are_the_same_steps() {
    let gpu = gpu();
    let (occ, _) = occupancy(&gpu, 3, "ahead");
    let s = sample(&gpu, 7, &occ[..FRAME_WORDS]);
    recorded_ahead_is_the_same(|| VoxelDecoder::new(&gpu, &VoxelConfig::tiny(), 1).unwrap(), &[&s], 4);
}

#[test]
fn f16_training_follows_f32() {
    // The tiny voxel decoder trained by the library trainer 20 steps on one frame of a scene
    // from the same start in f32 and in f16 (f16 operands of the trunks' products forward and
    // backward; f32 masters; the loss scaled by 2^16).
    let gpu = gpu();
    let (occ, _) = occupancy(&gpu, 3, "f16");
    let cfg = VoxelConfig::tiny();
    let s = sample(&gpu, 7, &occ[..FRAME_WORDS]);
    let losses =
        |precision| trainer_losses(&mut VoxelDecoder::new(&gpu, &cfg, 1).unwrap(), &[&s], 20, precision);
    let (full, half) = (losses(Precision::F32), losses(Precision::F16));
    let (worst, mean) = relative_gaps(&full, &half);
    eprintln!(
        "voxel decoder f16 against f32, 20 steps: loss {:.4} -> {:.4} (f32 {:.4} -> {:.4}); relative \
         difference at most {worst:.2e}, mean {mean:.2e}",
        half[0], half[19], full[0], full[19]
    );
    // Measured on lavapipe: at most 6.6e-5, mean 2.1e-5 (loss 1.49 -> 0.48).
    assert!(worst < 1e-3 && mean < 2e-4, "f16 strays from f32: worst {worst:.3e}, mean {mean:.3e}");
    assert!(full != half, "the f16 run must differ from the f32 one somewhere");
    assert!(mean_of(&full[15..]) < 0.5 * mean_of(&full[..5]), "the run must learn: {full:?}");
}
