//! Learning-rate schedules.
//!
//! The Vaswani et al. ("Attention Is All You Need", section 5.3) "noam" schedule used for every
//! Velox model: a linear warm-up to `peak` over `warmup` steps, then decay as 1/sqrt(step):
//!
//! lr(step) = peak * min(step / warmup, sqrt(warmup / step)),   step = 1, 2, ...
//!
//! The two branches meet at step == warmup, where lr == peak.
//!
//! Tests: `tests/training/train_primitives.rs`.

/// The noam schedule with its peak learning rate and warm-up length.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Noam {
    pub peak: f64,
    pub warmup: u64,
}

impl Noam {
    pub fn new(peak: f64, warmup: u64) -> Noam {
        Noam { peak, warmup }
    }

    /// The learning rate of `step` (counted from 1). Step 0, before any update, gives 0; a
    /// warm-up of 0 counts as 1 (no warm-up: peak at step 1, then the decay).
    pub fn lr(&self, step: u64) -> f64 {
        noam(self.peak, self.warmup, step)
    }
}

/// lr = peak * min(step / warmup, sqrt(warmup / step)); see [`Noam::lr`].
pub fn noam(peak: f64, warmup: u64, step: u64) -> f64 {
    if step == 0 {
        return 0.0;
    }
    let (s, w) = (step as f64, warmup.max(1) as f64);
    peak * (s / w).min((w / s).sqrt())
}

/// The factor of a linear cooldown over the last `cooldown` steps of a run of `total` steps: 1
/// until `total - cooldown`, then falling in equal steps to 1 / (cooldown + 1) at the last
/// step; 1 throughout when `cooldown` is 0. Depends on the step alone, so a resumed run
/// continues the same curve.
pub fn cooldown(total: u64, cooldown: u64, step: u64) -> f64 {
    let left = total.saturating_sub(step); // steps after this one
    if cooldown == 0 || left >= cooldown {
        return 1.0;
    }
    (left + 1) as f64 / (cooldown + 1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warms_up_linearly_peaks_then_decays_as_inverse_sqrt() {
        let s = Noam::new(4.9e-4, 4000);
        assert_eq!(s.lr(0), 0.0);
        assert!((s.lr(1) - 4.9e-4 / 4000.0).abs() < 1e-18);
        assert!((s.lr(2000) - 4.9e-4 / 2.0).abs() < 1e-15);
        assert!((s.lr(4000) - 4.9e-4).abs() < 1e-15);
        assert!((s.lr(16_000) - 4.9e-4 / 2.0).abs() < 1e-15);
        assert!((s.lr(400_000) - 4.9e-5).abs() < 1e-15);
        // Rises strictly to the peak, falls strictly after it.
        for k in 1..4000 {
            assert!(s.lr(k) < s.lr(k + 1));
        }
        for k in 4000..10_000 {
            assert!(s.lr(k) > s.lr(k + 1));
        }
    }

    #[test]
    fn cooldown_falls_linearly_over_the_last_steps() {
        assert_eq!(cooldown(100, 0, 100), 1.0);
        assert_eq!(cooldown(100, 10, 1), 1.0);
        assert_eq!(cooldown(100, 10, 90), 1.0);
        assert!((cooldown(100, 10, 91) - 10.0 / 11.0).abs() < 1e-15);
        assert!((cooldown(100, 10, 100) - 1.0 / 11.0).abs() < 1e-15);
        for k in 90..100 {
            assert!(cooldown(100, 10, k + 1) < cooldown(100, 10, k));
        }
        // Longer than the run: it starts at once.
        assert!(cooldown(5, 10, 1) < 1.0);
    }

    #[test]
    fn zero_warmup_means_no_warmup() {
        assert_eq!(noam(1e-4, 0, 1), 1e-4);
        assert!((noam(1e-4, 0, 4) - 0.5e-4).abs() < 1e-18);
    }
}
