//! Learning-rate schedules, as a pure function of the step (so a resumed run gets the same
//! rates without any saved state).

use serde::{Deserialize, Serialize};

/// The shape of the schedule after the warm-up.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", tag = "kind")]
pub enum Decay {
    /// `lr` throughout.
    Constant,
    /// `lr * gamma^floor(step / every)` (PyTorch `StepLR`).
    Step { every: u64, gamma: f64 },
    /// `min_lr + (lr - min_lr) (1 + cos(pi s / S)) / 2` over the `S` steps after the warm-up
    /// (PyTorch `CosineAnnealingLR` with `T_max = S`, `eta_min = min_lr`).
    Cosine { min_lr: f64 },
}

/// A learning-rate schedule: a linear warm-up from `lr / warmup` to `lr` over `warmup` steps,
/// then [`Decay`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Schedule {
    pub lr: f64,
    pub warmup: u64,
    pub decay: Decay,
}

impl Schedule {
    /// A constant rate.
    pub fn constant(lr: f64) -> Self {
        Schedule {
            lr,
            warmup: 0,
            decay: Decay::Constant,
        }
    }

    /// The learning rate of step `step` (0-based: the rate used by the `step + 1`-th update) in
    /// a run of `total` steps.
    pub fn lr_at(&self, step: u64, total: u64) -> f64 {
        if step < self.warmup {
            return self.lr * (step + 1) as f64 / self.warmup as f64;
        }
        let s = step - self.warmup;
        match self.decay {
            Decay::Constant => self.lr,
            Decay::Step { every, gamma } => self.lr * gamma.powi((s / every.max(1)) as i32),
            Decay::Cosine { min_lr } => {
                let span = total.saturating_sub(self.warmup).max(1);
                let frac = (s.min(span)) as f64 / span as f64;
                min_lr + (self.lr - min_lr) * (1.0 + (std::f64::consts::PI * frac).cos()) / 2.0
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rounding of a few float operations.
    const TOL: f64 = 1e-15;

    #[test]
    fn hand_computed_rates() {
        let c = Schedule::constant(0.1);
        assert_eq!(c.lr_at(0, 10), 0.1);
        assert_eq!(c.lr_at(999, 10), 0.1);

        let s = Schedule {
            lr: 1.0,
            warmup: 0,
            decay: Decay::Step {
                every: 3,
                gamma: 0.5,
            },
        };
        let rates: Vec<f64> = (0..7).map(|i| s.lr_at(i, 7)).collect();
        assert_eq!(rates, [1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.25]);

        // Warm-up of 2 steps, then cosine over the remaining 4 steps from 1.0 to 0.0:
        // s = 0, 1, 2, 3 -> (1 + cos(pi s / 4)) / 2 = 1, 0.853553..., 0.5, 0.146446...
        let w = Schedule {
            lr: 1.0,
            warmup: 2,
            decay: Decay::Cosine { min_lr: 0.0 },
        };
        let expected = [0.5, 1.0, 1.0, 0.8535533905932737, 0.5, 0.14644660940672627];
        for (i, e) in expected.iter().enumerate() {
            assert!((w.lr_at(i as u64, 6) - e).abs() < TOL, "step {i}");
        }
        // Past the end it stays at min_lr.
        assert!((w.lr_at(50, 6) - 0.0).abs() < TOL);
    }
}
