//! The questions the paper leaves open, from the same per-seed observations as the tables.
//!
//! - **Data efficiency** (the paper's discussion claims calibrated kernels adapt faster "with
//!   limited data"): FT runs that train on a fraction of their training set
//!   ([`super::collect::TrainSet::fraction`]) next to the full fine-tuning on the same set, per
//!   fraction the paired difference calibrated − standard per seed, its mean and 95% Student-t
//!   interval. `data_efficiency.json` (rows `{fraction, train_images, task, metric, standard,
//!   calibrated, diff_mean, ci95, n_seeds}`) and `data_efficiency_TASK_METRIC.png` (the gain
//!   against the number of training views, 95% band). The verdict's C7 reads the same cells.
//! - **Methods** (CAM-Convs extended to the fisheye, calibrated offsets that keep learning): per
//!   FT data set that has fine-tunings of the kinds beyond the paper's, every method's mean and
//!   interval over seeds and its paired difference to standard kernels. `methods.json` (rows
//!   `{method, lens, task, metric, mean, ci95, n_seeds, diff_vs_standard: {mean, ci95}}`) and
//!   `methods_TASK_METRIC.png`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::collect::{Study, TrainSet};
use super::stats::MeanCi;
use super::study::{
    paired_difference, Block, Cell, Observations, Task, CALIBRATED, CALIBRATED_LEARNED, CAMCONV,
    STANDARD,
};
use super::verdict::claim_metrics;
use crate::data::format::{Manifest, Split};
use crate::data::loader::fraction_len;
use crate::error::{Error, Result};
use crate::plots::{self, Curve, PlotSpec};

/// One set size of the data-efficiency series.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EfficiencyRow {
    /// The share of the training set, `1` for all of it.
    pub fraction: f64,
    /// Training images at that fraction.
    pub train_images: usize,
    pub task: String,
    pub metric: String,
    /// Means over the seeds of the difference.
    pub standard: f64,
    pub calibrated: f64,
    /// Mean over seeds of calibrated − standard (paired by seed).
    pub diff_mean: f64,
    /// 95% t-interval of that difference; `None` with fewer than two seeds.
    pub ci95: Option<[f64; 2]>,
    pub n_seeds: usize,
}

/// A mean and its interval.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Estimate {
    pub mean: f64,
    pub ci95: Option<[f64; 2]>,
}

/// One method on one lens.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MethodRow {
    /// `standard`, `calibrated`, `camconv`, `calibrated-learned`.
    pub method: String,
    /// The FT data set (`F195`).
    pub lens: String,
    pub task: String,
    pub metric: String,
    /// Mean over seeds and 95% t-interval of the metric.
    pub mean: f64,
    pub ci95: Option<[f64; 2]>,
    pub n_seeds: usize,
    /// Paired by seed: this method − standard kernels.
    pub diff_vs_standard: Estimate,
}

/// The methods of [`methods`], in table order.
pub const METHODS: [&str; 4] = [STANDARD, CALIBRATED, CAMCONV, CALIBRATED_LEARNED];

/// Per FT (task, data set label): the fraction, the training images at it, and the training
/// set (`PATH:SPLIT`).
type Fractions = BTreeMap<(Task, String), (f64, usize, String)>;

/// The data set label of the FT rows of each (task, training set, fraction), with the number of
/// training images at that fraction; `fraction` 1 for runs on the whole set.
fn fractions(study: &Study) -> Result<Fractions> {
    let mut out = BTreeMap::new();
    let mut sizes: BTreeMap<(PathBuf, String), usize> = BTreeMap::new();
    for row in study.rows.iter().filter(|r| r.cell.block == Block::Ft) {
        let Some(TrainSet {
            path,
            split,
            fraction,
        }) = &row.train_set
        else {
            continue;
        };
        let key = (path.clone(), split.clone());
        let n = match sizes.get(&key) {
            Some(n) => *n,
            None => {
                let manifest = Manifest::read(path)?;
                let s: Split = split.parse().map_err(|e: String| Error::Data {
                    path: path.clone(),
                    message: e,
                })?;
                let n = manifest.splits.get(s).len();
                sizes.insert(key, n);
                n
            }
        };
        let f = fraction.unwrap_or(1.0);
        let images = fraction_len(n, f);
        let set = format!("{}:{split}", path.display());
        out.insert((row.cell.task, row.cell.dataset.clone()), (f, images, set));
    }
    Ok(out)
}

/// The data-efficiency rows: for every training set that some FT run trained a fraction of,
/// every fraction (the whole set included) whose rows have both kernels, by task, metric and
/// fraction.
pub fn data_efficiency(study: &Study, obs: &Observations) -> Result<Vec<EfficiencyRow>> {
    let by_label = fractions(study)?;
    let partial_sets: Vec<&String> = by_label
        .values()
        .filter(|(f, _, _)| *f < 1.0)
        .map(|(_, _, set)| set)
        .collect();
    let mut rows = Vec::new();
    for ((task, label), (fraction, images, set)) in &by_label {
        if !partial_sets.contains(&set) {
            continue;
        }
        let cal = Cell::new(*task, Block::Ft, label, CALIBRATED);
        let std = cal.with_kernel(STANDARD);
        for metric in claim_metrics(*task) {
            let (a, b) = (obs.get(&cal, metric), obs.get(&std, metric));
            let d = paired_difference(&a, &b);
            if d.is_empty() {
                continue;
            }
            let paired = |v: &BTreeMap<u64, f64>| {
                let xs: Vec<f64> = d.keys().filter_map(|s| v.get(s).copied()).collect();
                xs.iter().sum::<f64>() / xs.len() as f64
            };
            let ci = MeanCi::of(&d.values().copied().collect::<Vec<_>>());
            rows.push(EfficiencyRow {
                fraction: *fraction,
                train_images: *images,
                task: task.name().to_string(),
                metric: metric.name().to_string(),
                standard: paired(&b),
                calibrated: paired(&a),
                diff_mean: ci.mean,
                ci95: ci.interval(),
                n_seeds: ci.n,
            });
        }
    }
    rows.sort_by(|a, b| {
        (a.task.as_str(), a.metric.as_str())
            .cmp(&(b.task.as_str(), b.metric.as_str()))
            .then(a.fraction.total_cmp(&b.fraction))
    });
    Ok(rows)
}

/// The method rows: every FT cell whose data set has a fine-tuning of a kind beyond the paper's
/// two, for each of [`METHODS`] observed there.
pub fn methods(obs: &Observations) -> Vec<MethodRow> {
    let mut rows = Vec::new();
    let lenses: Vec<Cell> = obs
        .cells()
        .into_iter()
        .filter(|c| c.block == Block::Ft && (c.kernel == CAMCONV || c.kernel == CALIBRATED_LEARNED))
        .map(|c| c.with_kernel(STANDARD))
        .collect();
    let mut seen = Vec::new();
    for std in lenses {
        if seen.contains(&std) {
            continue;
        }
        seen.push(std.clone());
        for metric in claim_metrics(std.task) {
            let reference = obs.get(&std, metric);
            for method in METHODS {
                let cell = std.with_kernel(method);
                let values = obs.get(&cell, metric);
                if values.is_empty() {
                    continue;
                }
                let m = MeanCi::of(&values.values().copied().collect::<Vec<_>>());
                let d = paired_difference(&values, &reference);
                let dci = MeanCi::of(&d.values().copied().collect::<Vec<_>>());
                rows.push(MethodRow {
                    method: method.to_string(),
                    lens: std.dataset.clone(),
                    task: std.task.name().to_string(),
                    metric: metric.name().to_string(),
                    mean: m.mean,
                    ci95: m.interval(),
                    n_seeds: m.n,
                    diff_vs_standard: Estimate {
                        mean: if d.is_empty() { f64::NAN } else { dci.mean },
                        ci95: dci.interval(),
                    },
                });
            }
        }
    }
    rows
}

/// Writes `data_efficiency.json` and its plots into `out` (nothing without rows); returns the
/// files written.
pub fn write_data_efficiency(rows: &[EfficiencyRow], out: &Path) -> Result<Vec<PathBuf>> {
    let groups = super::group_by(rows, |r| (r.task.as_str(), r.metric.as_str()));
    let plots = groups.into_iter().map(|((task, metric), points)| {
        let curve = Curve::with_intervals(
            format!("calibrated − standard ({metric})"),
            plots::CALIBRATED_BLUE,
            points
                .iter()
                .map(|r| (r.train_images as f64, r.diff_mean, r.ci95)),
        );
        let n = points.iter().map(|r| r.n_seeds).min().unwrap_or(0);
        let spec = PlotSpec {
            title: format!("FT {task}: calibrated − standard {metric} vs training views"),
            x_label: "fine-tuning views".into(),
            y_label: format!("{metric} difference (mean over {n} seeds, 95% t band)"),
            ..Default::default()
        };
        (
            format!("data_efficiency_{task}_{metric}.png"),
            spec,
            vec![curve],
        )
    });
    super::write_rows_and_plots(rows, out, "data_efficiency.json", plots)
}

/// Writes `methods.json` and its plots into `out` (nothing without rows); returns the files
/// written. The plot shows each method's difference to standard kernels with its interval, as
/// points along the method axis (1 = calibrated, 2 = camconv, 3 = calibrated-learned).
pub fn write_methods(rows: &[MethodRow], out: &Path) -> Result<Vec<PathBuf>> {
    let methods = rows.iter().filter(|r| r.method != STANDARD);
    let groups = super::group_by(methods, |r| {
        (r.lens.as_str(), r.task.as_str(), r.metric.as_str())
    });
    let colour = |m: &str| match m {
        CALIBRATED => plots::CALIBRATED_BLUE,
        CAMCONV => plots::CAMCONV_ORANGE,
        _ => plots::LEARNED_PURPLE,
    };
    let plots = groups
        .into_iter()
        .filter_map(|((lens, task, metric), points)| {
            let curves: Vec<Curve> = points
                .iter()
                .filter(|r| r.diff_vs_standard.mean.is_finite())
                .map(|r| {
                    let x = METHODS.iter().position(|m| *m == r.method).unwrap_or(0) as f64;
                    // A short horizontal segment per method, its band the 95% interval.
                    let d = &r.diff_vs_standard;
                    Curve::with_intervals(
                        r.method.clone(),
                        colour(&r.method),
                        [(x - 0.2, d.mean, d.ci95), (x + 0.2, d.mean, d.ci95)],
                    )
                })
                .collect();
            if curves.is_empty() {
                return None;
            }
            let spec = PlotSpec {
                title: format!("FT {lens} {task}: method − standard kernels, {metric}"),
                x_label: "1 calibrated, 2 camconv, 3 calibrated-learned".into(),
                y_label: format!("{metric} difference (mean over seeds, 95% t band)"),
                ..Default::default()
            };
            Some((format!("methods_{task}_{metric}.png"), spec, curves))
        });
    super::write_rows_and_plots(rows, out, "methods.json", plots)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::metrics::Metric;

    #[test]
    fn method_rows_pair_each_method_with_standard_kernels_by_seed() {
        let mut obs = Observations::default();
        let std = Cell::new(Task::Depth, Block::Ft, "F195", STANDARD);
        for (kernel, values) in [
            (STANDARD, [1.0, 2.0, 3.0]),
            (CALIBRATED, [0.9, 1.9, 2.9]),
            (CAMCONV, [1.1, 2.0, 3.3]),
        ] {
            for (s, v) in values.iter().enumerate() {
                obs.insert(&std.with_kernel(kernel), Metric::Rmse, s as u64, *v);
            }
        }
        let rows = methods(&obs);
        let rmse: Vec<&MethodRow> = rows.iter().filter(|r| r.metric == "rmse").collect();
        assert_eq!(rmse.len(), 3);
        let cal = rmse.iter().find(|r| r.method == CALIBRATED).unwrap();
        assert!((cal.diff_vs_standard.mean + 0.1).abs() < 1e-12);
        // The same difference for every seed: a zero-width interval.
        let [lo, hi] = cal.diff_vs_standard.ci95.unwrap();
        assert!((lo + 0.1).abs() < 1e-9 && (hi + 0.1).abs() < 1e-9);
        let cam = rmse.iter().find(|r| r.method == CAMCONV).unwrap();
        assert!((cam.diff_vs_standard.mean - 0.4 / 3.0).abs() < 1e-12);
        assert!((cam.mean - 6.4 / 3.0).abs() < 1e-12 && cam.n_seeds == 3);
        let dir = tempfile::tempdir().unwrap();
        let files = write_methods(&rows, dir.path()).unwrap();
        assert!(dir.path().join("methods.json").is_file(), "{files:?}");
        assert!(
            dir.path().join("methods_depth_rmse.png").is_file(),
            "{files:?}"
        );
        // Without a kind beyond the paper's there are no method rows.
        let mut paper = Observations::default();
        paper.insert(&std, Metric::Rmse, 0, 1.0);
        paper.insert(&std.with_kernel(CALIBRATED), Metric::Rmse, 0, 1.0);
        assert!(methods(&paper).is_empty());
    }

    #[test]
    fn efficiency_plots_and_json_are_written() {
        let rows: Vec<EfficiencyRow> = [(0.0625, 130, -0.05), (1.0, 2080, -0.02)]
            .into_iter()
            .map(|(fraction, train_images, d)| EfficiencyRow {
                fraction,
                train_images,
                task: "depth".into(),
                metric: "rmse".into(),
                standard: 0.6,
                calibrated: 0.6 + d,
                diff_mean: d,
                ci95: Some([d - 0.01, d + 0.01]),
                n_seeds: 3,
            })
            .collect();
        let dir = tempfile::tempdir().unwrap();
        write_data_efficiency(&rows, dir.path()).unwrap();
        let back: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join("data_efficiency.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(back[0]["train_images"], 130);
        assert!(dir.path().join("data_efficiency_depth_rmse.png").is_file());
        assert!(write_data_efficiency(&[], dir.path()).unwrap().is_empty());
    }
}
