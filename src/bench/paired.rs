//! Paired timing: the reference and the candidates interleaved, the medians of their times and
//! of the per-repetition ratios with a distribution-free interval, and the performance goals
//! computed from that interval.

use std::time::Instant;

use serde::Serialize;

use super::proc::cpu_seconds;
use super::Impl;

/// Medians of a paired measurement (milliseconds) and of the per-repetition ratios.
#[derive(Debug, Serialize)]
pub(super) struct Paired {
    pub(super) reference_ms: f64,
    pub(super) candidate_ms: f64,
    pub(super) ratio: f64,
    /// A distribution-free confidence interval (at least 95%) of the median per-repetition
    /// wall-time ratio ([`median_ci`]; none below 6 repetitions).
    pub(super) ratio_ci: Option<[f64; 2]>,
    /// The same from the process's CPU time (all threads, user + system) instead of wall time:
    /// on a machine loaded beyond its cores a run longer than a scheduler time slice is
    /// preempted more often than a short one, which inflates wall-time ratios; with one thread
    /// the CPU-time ratio is the work ratio (with more, it counts OpenMP's spinning too).
    pub(super) cpu_ratio: Option<f64>,
}

/// The performance goals of the calibrated layers (README, "Performance"): every 3x3 layer of
/// the `tiny` and `small` presets at most 1.3x `conv2d`, forward and forward+backward, and at
/// most 1.15x where input and output both have 64 channels or more (in every preset: `classic`'s
/// wider layers). `None`: the layer has no goal (explicit shapes, `classic`'s narrow layers).
pub(super) fn goal_limit(net: &str, c_in: i64, c_out: i64) -> Option<f64> {
    let wide = c_in >= 64 && c_out >= 64;
    match net {
        "tiny" | "small" => Some(if wide { 1.15 } else { 1.3 }),
        "classic" if wide => Some(1.15),
        _ => None,
    }
}

/// Whether a goal holds, computed from the ratio's interval: `Holds` when the whole interval is
/// at or below the limit, `Contradicted` when it is wholly above, else (or without an interval)
/// `Inconclusive`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub(super) enum Outcome {
    Holds,
    Contradicted,
    Inconclusive,
}

impl Outcome {
    pub(super) fn of(ci: Option<[f64; 2]>, limit: f64) -> Self {
        match ci {
            Some([_, hi]) if hi <= limit => Outcome::Holds,
            Some([lo, _]) if lo > limit => Outcome::Contradicted,
            _ => Outcome::Inconclusive,
        }
    }

    /// The short form of the table's last column.
    pub(super) fn mark(self) -> &'static str {
        match self {
            Outcome::Holds => "ok",
            Outcome::Contradicted => "OVER",
            Outcome::Inconclusive => "?",
        }
    }
}

/// A layer's goal ([`goal_limit`]) and its outcome for the forward and the forward+backward pass.
#[derive(Debug, Serialize)]
pub(super) struct Goal {
    pub(super) limit: f64,
    pub(super) forward: Outcome,
    pub(super) forward_backward: Outcome,
}

impl Goal {
    pub(super) fn of(net: &str, c_in: i64, c_out: i64, calibrated: &Impl) -> Option<Self> {
        let limit = goal_limit(net, c_in, c_out)?;
        Some(Goal {
            limit,
            forward: Outcome::of(calibrated.forward.ratio_ci, limit),
            forward_backward: Outcome::of(calibrated.forward_backward.ratio_ci, limit),
        })
    }
}

/// Wall time of `f` in milliseconds.
pub(super) fn time_ms(f: &mut dyn FnMut()) -> f64 {
    let start = Instant::now();
    f();
    start.elapsed().as_secs_f64() * 1e3
}

/// Wall and process CPU time of `f` in milliseconds.
pub(super) fn time_both_ms(f: &mut dyn FnMut()) -> (f64, Option<f64>) {
    let cpu0 = cpu_seconds();
    let wall = time_ms(f);
    let cpu = cpu_seconds().zip(cpu0).map(|(b, a)| (b - a) * 1e3);
    (wall, cpu)
}

/// A distribution-free confidence interval of the median of `sorted` (ascending), with
/// coverage at least 95%: the order statistics `x(j)` and `x(n + 1 - j)` (1-based), `j` the
/// largest with `P(Binomial(n, 1/2) <= j - 1) <= 0.025` (the number of values below the median
/// is binomial when they are exchangeable). `None` below 6 values (no such `j`). For 15
/// repetitions: `x(4)` and `x(12)`, coverage 96.5%; for 101 (`MAX_REPS`): `x(41)`, `x(61)`.
pub(super) fn median_ci(sorted: &[f64]) -> Option<[f64; 2]> {
    let n = sorted.len();
    let total = 2f64.powi(i32::try_from(n).ok()?);
    let (mut cdf, mut choose, mut j) = (0.0, 1.0, 0);
    for k in 0..n {
        cdf += choose / total; // P(X <= k)
        if cdf > 0.025 {
            break;
        }
        j = k + 1;
        choose *= (n - k) as f64 / (k + 1) as f64;
    }
    (j >= 1).then(|| [sorted[j - 1], sorted[n - j]])
}

pub(super) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n == 0 {
        f64::NAN
    } else if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Runs `reference` and every candidate `reps` times, interleaved (the order rotates each
/// repetition), after one warm-up call each; returns one [`Paired`] per candidate.
pub(super) fn paired(
    reps: usize,
    reference: &mut dyn FnMut(),
    candidates: &mut [&mut dyn FnMut()],
) -> Vec<Paired> {
    reference();
    for c in candidates.iter_mut() {
        c();
    }
    let n = candidates.len();
    let mut times = vec![Vec::with_capacity(reps); n + 1]; // slot 0: the reference
    for rep in 0..reps {
        // Rotate who goes first.
        for k in 0..=n {
            let slot = (k + rep) % (n + 1);
            let t = if slot == 0 {
                time_both_ms(reference)
            } else {
                time_both_ms(candidates[slot - 1])
            };
            times[slot].push(t);
        }
    }
    let wall = |v: &[(f64, Option<f64>)]| v.iter().map(|t| t.0).collect::<Vec<_>>();
    let ref_wall = wall(&times[0]);
    times[1..]
        .iter()
        .map(|c| {
            let cpu: Option<Vec<f64>> = c
                .iter()
                .zip(&times[0])
                .map(|(c, r)| Some(c.1? / r.1?.max(1e-6)))
                .collect();
            let mut ratios: Vec<f64> = c.iter().zip(&ref_wall).map(|(c, r)| c.0 / r).collect();
            ratios.sort_by(|a, b| a.total_cmp(b));
            Paired {
                reference_ms: median(ref_wall.clone()),
                candidate_ms: median(wall(c)),
                ratio_ci: median_ci(&ratios),
                ratio: median(ratios),
                cpu_ratio: cpu.map(median),
            }
        })
        .collect()
}
