//! The order in which training visits a dataset's samples (scenes, for the autoencoder), and
//! the generator of each sample of a step: pure functions of the seed and the step.
//!
//! Training reads the samples in passes (epochs) over the dataset, each pass in its own order.
//! Numbering the samples of that endless sequence by their position (0, 1, 2...), pass `e`
//! holds positions `e n .. (e + 1) n` of a dataset of `n` samples, in an order drawn from
//! `(seed, e)` alone.
//!
//! A step trains on a batch of `global_batch` slots (`g = 0, 1, ...`), the samples of every
//! micro-batch of every process together. Steps come in groups of `steps_per_scene` that
//! train on the same samples: slot `g` of step `s` holds position
//! `((s - 1) / steps_per_scene) * global_batch + g`, and its random draws come from
//! [`slot_rng`]`(seed, s, g)`. So the samples of any step follow from the seed, the step and
//! the dataset without replaying the passes before it (a resumed run repeats the
//! uninterrupted one), and they do not depend on how the global batch is split between
//! processes and micro-batches.
//!
//! Tests: `tests/data/data.rs` (the sample order) and `tools/tests/train_cli.rs`.

use velox_engine::rng::Rng;

/// The samples (indices into the dataset's name order) of pass `epoch` over `n` samples: name
/// order without a seed, else a shuffle drawn from `(seed, epoch)`.
pub fn epoch_order(n: usize, seed: Option<u64>, epoch: u64) -> Vec<usize> {
    let mut order: Vec<usize> = (0..n).collect();
    if let Some(seed) = seed {
        let mut rng = Rng::new(mix(seed, epoch));
        for i in (1..n).rev() {
            order.swap(i, rng.below(i as u32 + 1) as usize);
        }
    }
    order
}

/// The sample at `position` of the sequence of passes over `n` samples (`n` > 0).
pub fn scene_at(n: usize, seed: Option<u64>, position: u64) -> usize {
    let n64 = n as u64;
    epoch_order(n, seed, position / n64)[(position % n64) as usize]
}

/// The group of training step `step` (counted from 1): the steps of a group train on the same
/// samples, and group `k` starts at position `k * global_batch` (with one sample a step, the
/// position of the step's sample).
pub fn step_position(step: u64, steps_per_scene: u64) -> u64 {
    step.saturating_sub(1) / steps_per_scene.max(1)
}

/// The position of slot `slot` of step `step`'s global batch.
pub fn slot_position(step: u64, steps_per_scene: u64, global_batch: u64, slot: u64) -> u64 {
    step_position(step, steps_per_scene) * global_batch + slot
}

/// The sample that training step `step` (counted from 1) of a run seeded with `seed` trains on,
/// with one sample a step.
pub fn scene_of_step(n: usize, seed: u64, step: u64, steps_per_scene: u64) -> usize {
    scene_at(n, Some(seed), step_position(step, steps_per_scene))
}

/// The generator of slot `slot` of step `step` of a run seeded with `seed`: what the sample in
/// that slot draws (frames, points, noise), whichever process and micro-batch runs it.
pub fn slot_rng(seed: u64, step: u64, slot: u64) -> Rng {
    Rng::new(mix(mix(seed, step), slot))
}

/// The samples at successive positions, computing each pass's order once.
pub struct Order {
    n: usize,
    seed: u64,
    epoch: Option<(u64, Vec<usize>)>,
}

impl Order {
    /// The shuffled passes over `n` samples (`n` > 0) of a run seeded with `seed`.
    pub fn new(n: usize, seed: u64) -> Order {
        Order { n, seed, epoch: None }
    }

    /// The sample at `position`, as [`scene_at`] gives it.
    pub fn at(&mut self, position: u64) -> usize {
        let n = self.n as u64;
        let epoch = position / n;
        if self.epoch.as_ref().is_none_or(|(e, _)| *e != epoch) {
            self.epoch = Some((epoch, epoch_order(self.n, Some(self.seed), epoch)));
        }
        self.epoch.as_ref().expect("set above").1[(position % n) as usize]
    }
}

/// One generator seed per (seed, epoch): splitmix64's finaliser over both, so neighbouring
/// seeds or epochs give unrelated shuffles.
fn mix(seed: u64, epoch: u64) -> u64 {
    let mut z = seed ^ epoch.wrapping_add(1).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_pass_is_a_permutation_drawn_from_seed_and_epoch_alone() {
        for n in [1, 2, 7, 50] {
            for epoch in 0..6 {
                let mut o = epoch_order(n, Some(3), epoch);
                assert_eq!(o, epoch_order(n, Some(3), epoch), "the same pass twice");
                o.sort_unstable();
                assert_eq!(o, (0..n).collect::<Vec<_>>());
            }
            assert_eq!(epoch_order(n, None, 4), (0..n).collect::<Vec<_>>(), "name order without a seed");
        }
        let passes: Vec<Vec<usize>> = (0..8).map(|e| epoch_order(50, Some(3), e)).collect();
        assert!(passes.windows(2).all(|w| w[0] != w[1]), "passes are shuffled anew");
        assert_ne!(epoch_order(50, Some(3), 0), epoch_order(50, Some(4), 0), "seeds differ");
    }

    #[test]
    fn the_scene_of_a_step_follows_the_passes() {
        let (n, seed, per) = (3, 11, 4);
        let sequence: Vec<usize> = (0..4).flat_map(|e| epoch_order(n, Some(seed), e)).collect();
        for step in 1..=48u64 {
            let position = (step - 1) / per;
            assert_eq!(step_position(step, per), position);
            assert_eq!(scene_of_step(n, seed, step, per), sequence[position as usize], "step {step}");
        }
        // One step per scene: every step moves on.
        assert_eq!(step_position(5, 1), 4);
    }

    #[test]
    fn slots_of_a_step_follow_the_sequence_and_the_order_cache_agrees() {
        // Batches of 3, 2 steps on each: steps 1-2 take positions 0-2, steps 3-4 take 3-5...
        for (step, first) in [(1, 0), (2, 0), (3, 3), (4, 3), (5, 6)] {
            for g in 0..3 {
                assert_eq!(slot_position(step, 2, 3, g), first + g, "step {step} slot {g}");
            }
        }
        let mut order = Order::new(7, 5);
        for p in (0..40).chain([3, 100, 2]) {
            assert_eq!(order.at(p), scene_at(7, Some(5), p), "position {p}");
        }
        // Each slot of each step its own generator, the same every time it is asked for.
        let draw = |s, g| slot_rng(9, s, g).next_u32();
        assert_eq!(draw(4, 1), draw(4, 1));
        let draws: std::collections::HashSet<u32> =
            (1..20).flat_map(|s| (0..8).map(move |g| draw(s, g))).collect();
        assert_eq!(draws.len(), 19 * 8, "distinct generators");
    }
}
