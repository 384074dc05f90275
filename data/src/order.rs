//! The order in which training visits a dataset's scenes, as a pure function.
//!
//! Training reads the scenes in passes (epochs) over the dataset, each pass in its own order,
//! and stays on each scene for `steps_per_scene` steps. Numbering the scenes of that endless
//! sequence by their position (0, 1, 2...), pass `e` holds positions `e n .. (e + 1) n` of a
//! dataset of `n` scenes, in an order drawn from `(seed, e)` alone. So the scene of any step
//! follows from the seed, the step, `steps_per_scene` and the scene list, without replaying the
//! passes before it, and a run resumed at any step visits the scenes an uninterrupted one would.

use velox_engine::rng::Rng;

/// The scenes (indices into the dataset's name order) of pass `epoch` over `n` scenes: name
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

/// The scene at `position` of the sequence of passes over `n` scenes (`n` > 0).
pub fn scene_at(n: usize, seed: Option<u64>, position: u64) -> usize {
    let n64 = n as u64;
    epoch_order(n, seed, position / n64)[(position % n64) as usize]
}

/// The position in that sequence of the scene of training step `step` (counted from 1).
pub fn step_position(step: u64, steps_per_scene: u64) -> u64 {
    step.saturating_sub(1) / steps_per_scene.max(1)
}

/// The scene that training step `step` (counted from 1) of a run seeded with `seed` trains on.
pub fn scene_of_step(n: usize, seed: u64, step: u64, steps_per_scene: u64) -> usize {
    scene_at(n, Some(seed), step_position(step, steps_per_scene))
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
}
