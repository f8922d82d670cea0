//! The computed verdict on the paper's claims (`verdict.json`, `verdict.md`).
//!
//! Claims C1..C6 are read from the paper (Berenguel-Baeta et al., Sections 4.2-4.3 and the
//! conclusions); C7 from its discussion (faster adaptation with limited data). Each becomes one row per (claim, task, metric) (C5 one per calibration): a
//! per-seed difference of table values, its mean over seeds and 95% Student-t interval
//! ([`crate::report::stats::MeanCi`]), and the sign the claim predicts for the mean:
//!
//! - "A beats B" predicts `A - B < 0` for a lower-is-better metric (depth RMSE) and `> 0` for a
//!   higher-is-better one (delta1, mIoU, mAcc); "A is worse than B" the opposite sign.
//! - C3 compares gains: `(FT F195 calibrated - FT F195 standard) - (FT F165 calibrated - FT F165
//!   standard)`; "larger gain on F195" predicts the sign of "beats".
//! - C6: per seed, the gain `FT F195 calibrated - FT F195 standard` per radial bin (bins where
//!   both rows have a value), the mean over the outer third of those bins minus the mean over
//!   the inner third (a third is `max(1, n / 3)` bins); "grows with the distance" predicts the
//!   sign of "beats".
//! - C7 compares gains like C3: `(FT F195-1OF16 calibrated - FT F195-1OF16 standard) - (FT F195
//!   calibrated - FT F195 standard)` (the fine-tunings on 1/16 of the views against those on all
//!   of them, paired by seed); "larger with less data" predicts the sign of "beats".
//!
//! Outcome: `holds` when the whole interval lies on the predicted side of 0, `contradicted` when
//! it lies on the other side, else `inconclusive`; with fewer than 2 seeds there is no interval
//! and the outcome is `inconclusive` (with a `reason`). `half_width` is the smallest difference
//! the study could have told from 0. `reference_mean` is the mean over the same seeds of what
//! the difference is taken against: the B row of `A - B`, the F165 gain for C3, the inner
//! third's gain for C6.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::stats::MeanCi;
use super::study::{
    paired_difference, Block, Cell, Observations, PerSeed, Task, CALIBRATED, RECTIFIED, STANDARD,
};
use crate::eval::metrics::{Averaging, Metric};

/// The data sets the claims compare (a run that evaluates on none of them, such as a
/// field-of-view series lens, has no part in the verdict, nor in its `wall_s`).
pub const CLAIM_DATASETS: [&str; 2] = ["F195", "F165"];

/// The sign a claim predicts for its difference.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Sign {
    Negative,
    Positive,
}

/// What the interval says about a claim.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Outcome {
    Holds,
    Contradicted,
    Inconclusive,
}

/// One row of `verdict.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClaimRow {
    /// `C1`..`C7`.
    pub id: String,
    pub statement: String,
    /// `depth` or `segmentation`.
    pub task: String,
    pub metric: Metric,
    /// What is subtracted from what, e.g. `FT F195 calibrated - FT F195 standard`.
    pub compare: String,
    /// The difference per seed (seeds with every row the comparison needs, ascending).
    pub per_seed: Vec<f64>,
    /// Their mean (`None`: no seed has the rows).
    pub mean: Option<f64>,
    /// The 95% Student-t interval over seeds (`None` with fewer than 2 seeds).
    pub ci95: Option<[f64; 2]>,
    pub reference_mean: Option<f64>,
    pub expected: Sign,
    pub outcome: Outcome,
    /// The interval's half-width: the smallest difference this study could detect.
    pub half_width: Option<f64>,
    /// Why the outcome is inconclusive without an interval (missing rows, one seed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// `verdict.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Verdict {
    /// The sweep profile of the runs (`none` without one; comma-separated if they differ).
    pub profile: String,
    pub seeds: Vec<u64>,
    /// Test images per evaluation.
    pub test_images: u64,
    pub averaging: Averaging,
    /// Elapsed wall seconds of the runs the claims read (every seed; runs that evaluate on a
    /// [`CLAIM_DATASETS`] set): overlapping runs count once, the pause before a resumed study
    /// goes on not at all.
    pub wall_s: f64,
    /// Sum of the same runs' own wall seconds (more than `wall_s` when runs ran in parallel).
    #[serde(default)]
    pub run_seconds: f64,
    pub claims: Vec<ClaimRow>,
}

/// What the verdict is about, besides the observations.
#[derive(Clone, Debug, PartialEq)]
pub struct Meta {
    pub profile: String,
    pub test_images: u64,
    pub averaging: Averaging,
    pub wall_s: f64,
    pub run_seconds: f64,
}

/// Whether a claim says the first row is better or worse than the second.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Direction {
    Better,
    Worse,
}

/// The predicted sign of `a - b` for "a is `dir` than b" on `metric`.
pub fn expected_sign(metric: Metric, better: bool) -> Sign {
    match (metric.higher_is_better(), better) {
        (true, true) | (false, false) => Sign::Positive,
        _ => Sign::Negative,
    }
}

/// The outcome of an interval against the predicted sign.
pub fn outcome(ci: Option<[f64; 2]>, expected: Sign) -> Outcome {
    let Some([lo, hi]) = ci else {
        return Outcome::Inconclusive;
    };
    let (pos, neg) = (lo > 0.0, hi < 0.0);
    match (expected, pos, neg) {
        (Sign::Positive, true, _) | (Sign::Negative, _, true) => Outcome::Holds,
        (Sign::Positive, _, true) | (Sign::Negative, true, _) => Outcome::Contradicted,
        _ => Outcome::Inconclusive,
    }
}

/// How a claim's per-seed value is made.
enum Compare {
    /// `a - b`.
    Diff(Cell, Cell),
    /// `(a.0 - a.1) - (b.0 - b.1)`.
    DiffOfDiff((Cell, Cell), (Cell, Cell)),
    /// Outer third minus inner third of the radial curve of `a - b`.
    RadialOuterInner(Cell, Cell),
}

impl Compare {
    fn describe(&self) -> String {
        match self {
            Compare::Diff(a, b) => format!("{a} - {b}"),
            Compare::DiffOfDiff((a0, a1), (b0, b1)) => format!("({a0} - {a1}) - ({b0} - {b1})"),
            Compare::RadialOuterInner(a, b) => {
                format!("outer third - inner third of the radial bins of ({a} - {b})")
            }
        }
    }

    /// Per seed: the difference and its reference.
    fn per_seed(&self, obs: &Observations, m: Metric) -> (PerSeed, PerSeed) {
        match self {
            Compare::Diff(a, b) => {
                let (va, vb) = (obs.get(a, m), obs.get(b, m));
                let d = paired_difference(&va, &vb);
                let r = vb.into_iter().filter(|(s, _)| d.contains_key(s)).collect();
                (d, r)
            }
            Compare::DiffOfDiff((a0, a1), (b0, b1)) => {
                let ga = paired_difference(&obs.get(a0, m), &obs.get(a1, m));
                let gb = paired_difference(&obs.get(b0, m), &obs.get(b1, m));
                let d = paired_difference(&ga, &gb);
                let r = gb.into_iter().filter(|(s, _)| d.contains_key(s)).collect();
                (d, r)
            }
            Compare::RadialOuterInner(a, b) => {
                let get = |c: &Cell| obs.radial.get(&(c.clone(), m)).cloned().unwrap_or_default();
                let (ca, cb) = (get(a), get(b));
                let (mut d, mut r) = (PerSeed::new(), PerSeed::new());
                for (seed, xa) in &ca {
                    let Some(xb) = cb.get(seed) else { continue };
                    if let Some((outer, inner)) = outer_inner(xa, xb) {
                        d.insert(*seed, outer - inner);
                        r.insert(*seed, inner);
                    }
                }
                (d, r)
            }
        }
    }

    fn cells(&self) -> Vec<&Cell> {
        match self {
            Compare::Diff(a, b) | Compare::RadialOuterInner(a, b) => vec![a, b],
            Compare::DiffOfDiff((a, b), (c, d)) => vec![a, b, c, d],
        }
    }
}

/// The mean gain `a - b` over the outer and over the inner third of the bins where both curves
/// are finite (`None` with fewer than 2 such bins).
pub fn outer_inner(a: &[f64], b: &[f64]) -> Option<(f64, f64)> {
    let gain: Vec<f64> = a
        .iter()
        .zip(b)
        .map(|(x, y)| x - y)
        .filter(|g| g.is_finite())
        .collect();
    if gain.len() < 2 {
        return None;
    }
    let third = (gain.len() / 3).max(1);
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    Some((mean(&gain[gain.len() - third..]), mean(&gain[..third])))
}

/// The FT data set label of the smallest data-efficiency fraction (evaluation
/// `f195-1of16-KERNEL`, experiments/data-efficiency), read by claim C7.
pub const SMALLEST_F195_SET: &str = "F195-1OF16";

struct ClaimSpec {
    id: &'static str,
    statement: &'static str,
    direction: Direction,
    compares: Vec<Compare>,
}

fn claims(task: Task) -> Vec<ClaimSpec> {
    use Block::{Bl, Ft};
    let c = |block, set: &str, kernel: &str| Cell::new(task, block, set, kernel);
    // The calibrated kernels against the standard ones, on one block and data set.
    let gain = |block, set: &str| (c(block, set, CALIBRATED), c(block, set, STANDARD));
    let diff = |(a, b): (Cell, Cell)| Compare::Diff(a, b);
    let claim = |id, statement, direction, compares| ClaimSpec {
        id,
        statement,
        direction,
        compares,
    };
    let (f195_cal, f195_std) = gain(Ft, "F195");
    vec![
        claim(
            "C1",
            "After fine-tuning on F195, calibrated kernels beat standard kernels.",
            Direction::Better,
            vec![diff(gain(Ft, "F195"))],
        ),
        claim(
            "C2",
            "After fine-tuning on F165, calibrated kernels beat standard kernels.",
            Direction::Better,
            vec![diff(gain(Ft, "F165"))],
        ),
        claim(
            "C3",
            "The calibrated kernels' gain after fine-tuning is larger on F195 (wider field of \
             view) than on F165.",
            Direction::Better,
            vec![Compare::DiffOfDiff(gain(Ft, "F195"), gain(Ft, "F165"))],
        ),
        claim(
            "C4",
            "After fine-tuning, standard kernels on rectified F165 images are worse than \
             standard kernels on the F165 fisheye images.",
            Direction::Worse,
            vec![Compare::Diff(
                c(Ft, "F165", RECTIFIED),
                c(Ft, "F165", STANDARD),
            )],
        ),
        claim(
            "C5",
            "Before fine-tuning (BL, trained on Pers), calibrated kernels are slightly worse \
             than standard kernels on F195 and on F165.",
            Direction::Worse,
            vec![diff(gain(Bl, "F195")), diff(gain(Bl, "F165"))],
        ),
        claim(
            "C6",
            "After fine-tuning on F195, the calibrated kernels' gain grows with the distance to \
             the principal point.",
            Direction::Better,
            vec![Compare::RadialOuterInner(f195_cal, f195_std)],
        ),
        claim(
            "C7",
            "The calibrated kernels' gain after fine-tuning on F195 is larger with limited \
             fine-tuning data (1/16 of the views) than with all of them (the paper's discussion: \
             faster domain adaptation with limited data).",
            Direction::Better,
            vec![Compare::DiffOfDiff(
                gain(Ft, SMALLEST_F195_SET),
                gain(Ft, "F195"),
            )],
        ),
    ]
}

/// The metrics each claim is checked on.
pub fn claim_metrics(task: Task) -> [Metric; 2] {
    match task {
        Task::Depth => [Metric::Rmse, Metric::Delta1],
        Task::Segmentation => [Metric::MIoU, Metric::MAcc],
    }
}

/// The verdict of `obs`: every claim for every task that has any observed row.
pub fn verdict(obs: &Observations, meta: &Meta) -> Verdict {
    let seeds: Vec<u64> = obs.seeds().into_iter().collect();
    let tasks: Vec<Task> = [Task::Depth, Task::Segmentation]
        .into_iter()
        .filter(|t| obs.values.keys().any(|(c, _)| c.task == *t))
        .collect();
    let mut rows = Vec::new();
    // Claim order first, then task and metric.
    for i in 0..claims(Task::Depth).len() {
        for &task in &tasks {
            let spec = &claims(task)[i];
            for cmp in &spec.compares {
                for m in claim_metrics(task) {
                    rows.push(row(obs, spec, cmp, task, m));
                }
            }
        }
    }
    Verdict {
        profile: meta.profile.clone(),
        seeds,
        test_images: meta.test_images,
        averaging: meta.averaging,
        wall_s: meta.wall_s,
        run_seconds: meta.run_seconds,
        claims: rows,
    }
}

fn row(obs: &Observations, spec: &ClaimSpec, cmp: &Compare, task: Task, m: Metric) -> ClaimRow {
    let (d, r) = cmp.per_seed(obs, m);
    let per_seed: Vec<f64> = d.values().copied().collect();
    let expected = expected_sign(m, spec.direction == Direction::Better);
    let ci = MeanCi::of(&per_seed);
    let missing: Vec<String> = cmp
        .cells()
        .into_iter()
        .filter(|c| obs.get(c, m).is_empty())
        .map(|c| c.to_string())
        .collect();
    let reason = if !missing.is_empty() {
        Some(format!("no results for {}", missing.join(", ")))
    } else if per_seed.is_empty() {
        Some("no seed has every row of the comparison".to_string())
    } else if per_seed.len() < 2 {
        Some(format!(
            "{} seed: an interval needs >= 2 seeds",
            per_seed.len()
        ))
    } else {
        None
    };
    let interval = ci
        .interval()
        .filter(|[lo, hi]| lo.is_finite() && hi.is_finite());
    ClaimRow {
        id: spec.id.to_string(),
        statement: spec.statement.to_string(),
        task: task.name().to_string(),
        metric: m,
        compare: cmp.describe(),
        mean: (!per_seed.is_empty()).then_some(ci.mean),
        ci95: interval,
        reference_mean: (!r.is_empty()).then(|| r.values().sum::<f64>() / r.len() as f64),
        expected,
        outcome: outcome(interval, expected),
        half_width: interval.and(ci.half_width),
        reason,
        per_seed,
    }
}

/// `n = N` when every row has all the seeds, else the range of the rows' seed counts (a study
/// may add seeds to some experiments only: each row pairs the seeds both of its sides have).
fn seed_counts(v: &Verdict) -> String {
    let counts = v.claims.iter().map(|c| c.per_seed.len()).filter(|&n| n > 0);
    let (lo, hi) = (counts.clone().min(), counts.max());
    match (lo, hi) {
        (Some(lo), Some(hi)) if lo != hi => {
            format!("n = {lo}-{hi} per row: the seeds both sides of a row have, see *per seed*")
        }
        _ => format!("n = {}", v.seeds.len()),
    }
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map(|x| format!("{x:+.4}")).unwrap_or_else(|| "–".into())
}

/// `verdict.md`: the claims, then one table row per verdict row.
pub fn markdown(v: &Verdict) -> String {
    let mut s = format!(
        "## Verdict on the paper's claims\n\nProfile `{}`, seeds {:?} ({}), {} test images \
         per evaluation, depth metrics averaged `{}` (segmentation: one confusion matrix over \
         the test set), elapsed wall time of the runs on F195 and F165 {:.0} s (the sum of their own wall times: {:.0} s; parallel runs overlap). Differences are per seed, paired \
         (the same seed's rows, the same test images); mean and 95% Student-t interval over \
         seeds; ± is the half-width: the smallest difference this study could detect. \
         `holds` / `contradicted`: the whole interval on the predicted / the other side of 0.\n\n",
        v.profile,
        v.seeds,
        seed_counts(v),
        v.test_images,
        v.averaging,
        v.wall_s,
        v.run_seconds
    );
    let mut statements = BTreeMap::new();
    for c in &v.claims {
        statements
            .entry(c.id.clone())
            .or_insert(c.statement.clone());
    }
    for (id, st) in &statements {
        s += &format!("- **{id}**: {st}\n");
    }
    s += "\n| claim | task | metric | difference | predicted | per seed | mean | 95% CI | ± | \
          reference | outcome |\n|---|---|---|---|---|---|---:|---|---:|---:|---|\n";
    for c in &v.claims {
        let per_seed: Vec<String> = c.per_seed.iter().map(|x| format!("{x:+.4}")).collect();
        s += &format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | **{}**{} |\n",
            c.id,
            c.task,
            c.metric,
            c.compare,
            match c.expected {
                Sign::Negative => "< 0",
                Sign::Positive => "> 0",
            },
            per_seed.join(", "),
            fmt_opt(c.mean),
            c.ci95
                .map(|[a, b]| format!("[{a:+.4}, {b:+.4}]"))
                .unwrap_or_else(|| "–".into()),
            c.half_width
                .map(|h| format!("{h:.4}"))
                .unwrap_or_else(|| "–".into()),
            c.reference_mean
                .map(|x| format!("{x:.4}"))
                .unwrap_or_else(|| "–".into()),
            match c.outcome {
                Outcome::Holds => "holds",
                Outcome::Contradicted => "contradicted",
                Outcome::Inconclusive => "inconclusive",
            },
            c.reason
                .as_ref()
                .map(|r| format!(" ({r})"))
                .unwrap_or_default()
        );
    }
    let count = |o: Outcome| v.claims.iter().filter(|c| c.outcome == o).count();
    s += &format!(
        "\n{} rows: {} hold, {} contradicted, {} inconclusive.\n",
        v.claims.len(),
        count(Outcome::Holds),
        count(Outcome::Contradicted),
        count(Outcome::Inconclusive)
    );
    if v.seeds.len() < 2 {
        s += "\nWith one seed there are no intervals: an interval over seeds needs >= 2 seeds \
              (`calibconv sweep ... --seeds 0,1,2`), so every outcome is inconclusive.\n";
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn meta() -> Meta {
        Meta {
            profile: "quick".into(),
            test_images: 160,
            averaging: Averaging::PerImage,
            wall_s: 12.0,
            run_seconds: 20.0,
        }
    }

    /// FT F195 depth RMSE: standard 1.0 in every seed, calibrated `1.0 + d_s`.
    fn ft_f195(d: &[f64]) -> Observations {
        let mut o = Observations::default();
        let std = Cell::new(Task::Depth, Block::Ft, "F195", STANDARD);
        let cal = std.with_kernel(CALIBRATED);
        for (s, x) in d.iter().enumerate() {
            o.insert(&std, Metric::Rmse, s as u64, 1.0);
            o.insert(&cal, Metric::Rmse, s as u64, 1.0 + x);
            // delta1 moves the other way: calibrated higher by -d.
            o.insert(&std, Metric::Delta1, s as u64, 0.5);
            o.insert(&cal, Metric::Delta1, s as u64, 0.5 - x);
        }
        o
    }

    fn find<'a>(v: &'a Verdict, id: &str, m: Metric) -> &'a ClaimRow {
        v.claims
            .iter()
            .find(|c| c.id == id && c.metric == m)
            .unwrap()
    }

    #[test]
    fn c7_compares_the_gain_on_a_sixteenth_with_the_gain_on_all_views() {
        let mut o = ft_f195(&[-0.02, -0.03, -0.01]);
        let std = Cell::new(Task::Depth, Block::Ft, SMALLEST_F195_SET, STANDARD);
        for (s, d) in [-0.10, -0.12, -0.08].iter().enumerate() {
            o.insert(&std, Metric::Rmse, s as u64, 1.5);
            o.insert(
                &std.with_kernel(CALIBRATED),
                Metric::Rmse,
                s as u64,
                1.5 + d,
            );
        }
        let v = verdict(&o, &meta());
        let r = find(&v, "C7", Metric::Rmse);
        // Per seed: -0.10 - -0.02, -0.12 - -0.03, -0.08 - -0.01.
        for (got, want) in r.per_seed.iter().zip([-0.08, -0.09, -0.07]) {
            assert!((got - want).abs() < 1e-12, "{:?}", r.per_seed);
        }
        assert_eq!((r.expected, r.outcome), (Sign::Negative, Outcome::Holds));
        // Without the small-set rows: inconclusive, naming what is missing.
        let r = find(
            &verdict(&ft_f195(&[-0.02, -0.03]), &meta()),
            "C7",
            Metric::Rmse,
        )
        .clone();
        assert_eq!(r.outcome, Outcome::Inconclusive);
        assert!(r.reason.unwrap().contains("F195-1OF16"));
    }

    #[test]
    fn signs_follow_the_metric_direction() {
        // "calibrated beats standard": RMSE lower is better -> calibrated - standard < 0.
        assert_eq!(expected_sign(Metric::Rmse, true), Sign::Negative);
        assert_eq!(expected_sign(Metric::Delta1, true), Sign::Positive);
        assert_eq!(expected_sign(Metric::MIoU, true), Sign::Positive);
        assert_eq!(expected_sign(Metric::MAcc, false), Sign::Negative);
        assert_eq!(expected_sign(Metric::Rmse, false), Sign::Positive);
        assert_eq!(outcome(Some([-0.3, -0.1]), Sign::Negative), Outcome::Holds);
        assert_eq!(
            outcome(Some([0.1, 0.3]), Sign::Negative),
            Outcome::Contradicted
        );
        assert_eq!(
            outcome(Some([-0.1, 0.3]), Sign::Negative),
            Outcome::Inconclusive
        );
        assert_eq!(outcome(Some([0.1, 0.3]), Sign::Positive), Outcome::Holds);
        assert_eq!(outcome(None, Sign::Positive), Outcome::Inconclusive);
    }

    #[test]
    fn c1_holds_when_calibrated_is_clearly_lower() {
        // Differences -0.10, -0.12, -0.08: mean -0.1, sd 0.02, h = 4.3027 * 0.02 / sqrt 3.
        let v = verdict(&ft_f195(&[-0.10, -0.12, -0.08]), &meta());
        let r = find(&v, "C1", Metric::Rmse);
        assert_eq!(r.compare, "FT F195 calibrated - FT F195 standard");
        assert_eq!(r.expected, Sign::Negative);
        assert_eq!(r.outcome, Outcome::Holds);
        assert!((r.mean.unwrap() + 0.1).abs() < 1e-12);
        let h = 4.302_652_73 * 0.02 / 3f64.sqrt();
        assert!((r.half_width.unwrap() - h).abs() < 1e-6);
        assert!((r.ci95.unwrap()[1] - (-0.1 + h)).abs() < 1e-6);
        assert_eq!(r.reference_mean, Some(1.0));
        assert_eq!(r.per_seed.len(), 3);
        // delta1 rose by 0.1: positive expected, holds too.
        let r = find(&v, "C1", Metric::Delta1);
        assert_eq!((r.expected, r.outcome), (Sign::Positive, Outcome::Holds));
        assert_eq!(v.seeds, [0, 1, 2]);
        // Rows without results (F165, BL, rectified) are inconclusive and say why.
        let r = find(&v, "C2", Metric::Rmse);
        assert_eq!(r.outcome, Outcome::Inconclusive);
        assert!(
            r.reason.as_ref().unwrap().contains("FT F165 calibrated"),
            "{r:?}"
        );
        assert!(r.mean.is_none() && r.ci95.is_none());
        // Depth only: no segmentation rows.
        assert!(v.claims.iter().all(|c| c.task == "depth"));
        // Every row with results has the 3 seeds (rows without results do not count).
        assert!(markdown(&v).contains("seeds [0, 1, 2] (n = 3)"));
    }

    #[test]
    fn rows_with_fewer_seeds_give_the_range_of_counts() {
        let mut v = verdict(&ft_f195(&[-0.10, -0.12, -0.08]), &meta());
        let i = v
            .claims
            .iter()
            .position(|c| c.metric == Metric::Delta1)
            .unwrap();
        v.claims[i].per_seed.truncate(2);
        let md = markdown(&v);
        assert!(md.contains("seeds [0, 1, 2] (n = 2-3 per row"), "{md}");
    }

    #[test]
    fn c1_contradicted_and_inconclusive() {
        let v = verdict(&ft_f195(&[0.10, 0.12, 0.08]), &meta());
        assert_eq!(find(&v, "C1", Metric::Rmse).outcome, Outcome::Contradicted);
        assert_eq!(
            find(&v, "C1", Metric::Delta1).outcome,
            Outcome::Contradicted
        );
        // The measured seeds: +0.054, -0.075, +0.025: the interval spans 0.
        let v = verdict(&ft_f195(&[0.054, -0.075, 0.025]), &meta());
        let r = find(&v, "C1", Metric::Rmse);
        assert_eq!(r.outcome, Outcome::Inconclusive);
        assert!(r.reason.is_none());
        let [lo, hi] = r.ci95.unwrap();
        assert!(lo < 0.0 && hi > 0.0 && r.half_width.unwrap() > 0.1);
    }

    #[test]
    fn one_seed_gives_no_interval() {
        let v = verdict(&ft_f195(&[-0.5]), &meta());
        let r = find(&v, "C1", Metric::Rmse);
        assert_eq!(r.outcome, Outcome::Inconclusive);
        assert_eq!((r.ci95, r.half_width), (None, None));
        assert_eq!(r.mean, Some(-0.5));
        assert!(r.reason.as_ref().unwrap().contains(">= 2 seeds"));
        let md = markdown(&v);
        assert!(md.contains("needs >= 2 seeds"), "{md}");
        let json = serde_json::to_value(&v).unwrap();
        assert!(json["claims"][0]["ci95"].is_null());
        assert_eq!(json["averaging"], "per-image");
        assert_eq!(json["claims"][0]["expected"], "negative");
        assert_eq!(json["claims"][0]["outcome"], "inconclusive");
    }

    #[test]
    fn c3_is_a_difference_of_gains_and_c5_has_both_calibrations() {
        let mut o = Observations::default();
        let t = Task::Segmentation;
        for s in 0..3u64 {
            let e = s as f64 * 0.001;
            let put = |o: &mut Observations, b, set: &str, k: &str, v: f64| {
                o.insert(&Cell::new(t, b, set, k), Metric::MIoU, s, v + e)
            };
            // Gains: F195 +0.05, F165 +0.01 -> C3 = +0.04 (expected positive for mIoU).
            put(&mut o, Block::Ft, "F195", STANDARD, 0.20);
            put(&mut o, Block::Ft, "F195", CALIBRATED, 0.25 + e);
            put(&mut o, Block::Ft, "F165", STANDARD, 0.20);
            put(&mut o, Block::Ft, "F165", CALIBRATED, 0.21);
            // BL: calibrated lower on both: C5 (worse) holds.
            put(&mut o, Block::Bl, "F195", STANDARD, 0.18);
            put(&mut o, Block::Bl, "F195", CALIBRATED, 0.13 - e);
            put(&mut o, Block::Bl, "F165", STANDARD, 0.17);
            put(&mut o, Block::Bl, "F165", CALIBRATED, 0.13);
        }
        let v = verdict(&o, &meta());
        let c3 = find(&v, "C3", Metric::MIoU);
        assert!(c3
            .compare
            .starts_with("(FT F195 calibrated - FT F195 standard) - (FT F165"));
        // per seed 0.04 + e: mean 0.041.
        assert!((c3.mean.unwrap() - 0.041).abs() < 1e-12);
        assert!((c3.reference_mean.unwrap() - 0.01).abs() < 1e-12);
        assert_eq!((c3.expected, c3.outcome), (Sign::Positive, Outcome::Holds));
        let c5: Vec<&ClaimRow> = v
            .claims
            .iter()
            .filter(|c| c.id == "C5" && c.metric == Metric::MIoU)
            .collect();
        assert_eq!(c5.len(), 2);
        assert!(c5[0].compare.contains("BL F195") && c5[1].compare.contains("BL F165"));
        assert!(c5
            .iter()
            .all(|c| c.expected == Sign::Negative && c.outcome == Outcome::Holds));
    }

    #[test]
    fn c6_outer_minus_inner_third_of_the_radial_gain() {
        // 6 bins (the last empty in both); standard 1.0, calibrated gains -0.0, -0.1, -0.2,
        // -0.3, -0.4 over the 5 finite bins: thirds of 1 bin: outer -0.4 - inner 0.0 = -0.4.
        let mut o = Observations::default();
        let std = Cell::new(Task::Depth, Block::Ft, "F195", STANDARD);
        let cal = std.with_kernel(CALIBRATED);
        for s in 0..2u64 {
            let jitter = s as f64 * 0.01;
            let b: Vec<f64> = vec![1.0, 1.0, 1.0, 1.0, 1.0, f64::NAN];
            let a: Vec<f64> = (0..6)
                .map(|i| {
                    if i == 5 {
                        f64::NAN
                    } else {
                        1.0 - 0.1 * i as f64 - jitter * i as f64
                    }
                })
                .collect();
            o.radial
                .entry((std.clone(), Metric::Rmse))
                .or_default()
                .insert(s, b);
            o.radial
                .entry((cal.clone(), Metric::Rmse))
                .or_default()
                .insert(s, a);
            o.insert(&std, Metric::Rmse, s, 1.0);
            o.insert(&cal, Metric::Rmse, s, 0.8);
        }
        let v = verdict(&o, &meta());
        let r = find(&v, "C6", Metric::Rmse);
        assert!((r.per_seed[0] + 0.4).abs() < 1e-12, "{:?}", r.per_seed);
        assert!((r.per_seed[1] + 0.44).abs() < 1e-12);
        assert_eq!(r.reference_mean, Some(0.0));
        assert_eq!((r.expected, r.outcome), (Sign::Negative, Outcome::Holds));
        assert_eq!(outer_inner(&[1.0], &[0.0]), None);
        // 7 bins: thirds of 2.
        let (outer, inner) = outer_inner(&[0., 1., 2., 3., 4., 5., 6.], &[0.0; 7]).unwrap();
        assert_eq!((outer, inner), (5.5, 0.5));
    }
}
