//! The calibrated kernels' gain as a function of the field of view (beyond the paper, which has
//! two lenses): for every fine-tuned (FT) data set evaluated with both standard and calibrated
//! kernels, the paired difference calibrated − standard per seed, its mean and 95% Student-t
//! interval over seeds, against the field of view of the data set's camera (`fov_deg` of the
//! camera file its evaluations name). Written as `fov_gain.json` (rows `{fov_deg, dataset, task,
//! metric, mean, ci95, n_seeds}`), `fov_gain.png` (depth RMSE, the paper's headline metric, or
//! the first metric observed) and `fov_gain_TASK_METRIC.png` for every claim metric.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::collect::Study;
use super::stats::MeanCi;
use super::study::{paired_difference, Block, Cell, Observations, Task, CALIBRATED, STANDARD};
use super::tables::comparison_pairs;
use super::verdict::claim_metrics;
use crate::camera::{self, CameraModel};
use crate::error::{Error, Result};
use crate::plots::{Curve, PlotSpec};

/// One point of the curve.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FovRow {
    pub fov_deg: f64,
    /// The table's data-set label (`F195`, `KB120`).
    pub dataset: String,
    pub task: String,
    pub metric: String,
    /// Mean over seeds of calibrated − standard.
    pub mean: f64,
    /// 95% t-interval over seeds; `None` with fewer than two seeds.
    pub ci95: Option<[f64; 2]>,
    pub n_seeds: usize,
}

/// The field of view (degrees) of each FT data set, from the camera file of its evaluations.
fn fov_by_dataset(study: &Study) -> Result<BTreeMap<(Task, String), f64>> {
    let mut out = BTreeMap::new();
    // (Runs on a fraction of their training set belong to the data-efficiency series.)
    let whole =
        |r: &&super::collect::Row| r.train_set.as_ref().is_none_or(|t| t.fraction.is_none());
    for row in study
        .rows
        .iter()
        .filter(|r| r.cell.block == Block::Ft)
        .filter(whole)
    {
        let key = (row.cell.task, row.cell.dataset.clone());
        if out.contains_key(&key) {
            continue;
        }
        let Some(serde_json::Value::String(file)) = row.record.about.other.get("camera_file")
        else {
            continue;
        };
        let cam = camera::load(file).map_err(|e| {
            Error::InvalidArgument(format!(
                "{}: camera_file {file}: {e}",
                row.dir.join("metrics.json").display()
            ))
        })?;
        // Degrees to 1e-6 (the radians round trip leaves 239.99999999999997 for 240).
        out.insert(key, (cam.fov().to_degrees() * 1e6).round() / 1e6);
    }
    Ok(out)
}

/// The rows of the curve, by task, metric and field of view; empty unless at least two FT
/// data sets of one task have both kernels.
pub fn fov_gain(study: &Study, obs: &Observations) -> Result<Vec<FovRow>> {
    let fovs = fov_by_dataset(study)?;
    let mut rows = Vec::new();
    for task in [Task::Depth, Task::Segmentation] {
        let mut task_rows = Vec::new();
        // The FT calibrated − standard pairs the difference table compares.
        let pairs: Vec<(Cell, Cell)> = comparison_pairs(obs, task)
            .into_iter()
            .filter(|(a, b)| a.block == Block::Ft && a.kernel == CALIBRATED && b.kernel == STANDARD)
            .collect();
        for metric in claim_metrics(task) {
            for (cal, std) in &pairs {
                let Some(&fov_deg) = fovs.get(&(task, cal.dataset.clone())) else {
                    continue;
                };
                let d = paired_difference(&obs.get(cal, metric), &obs.get(std, metric));
                if d.is_empty() {
                    continue;
                }
                let xs: Vec<f64> = d.values().copied().collect();
                let ci = MeanCi::of(&xs);
                task_rows.push(FovRow {
                    fov_deg,
                    dataset: cal.dataset.clone(),
                    task: task.name().to_string(),
                    metric: metric.name().to_string(),
                    mean: ci.mean,
                    ci95: ci.interval(),
                    n_seeds: ci.n,
                });
            }
        }
        let datasets: std::collections::BTreeSet<&str> =
            task_rows.iter().map(|r| r.dataset.as_str()).collect();
        if datasets.len() >= 2 {
            rows.extend(task_rows);
        }
    }
    rows.sort_by(|a, b| {
        (a.task.as_str(), a.metric.as_str())
            .cmp(&(b.task.as_str(), b.metric.as_str()))
            .then(a.fov_deg.total_cmp(&b.fov_deg))
    });
    Ok(rows)
}

/// Writes `fov_gain.json` and the plots into `out` (nothing when `rows` is empty); returns the
/// files written.
pub fn write_fov_gain(rows: &[FovRow], out: &Path) -> Result<Vec<PathBuf>> {
    let groups = super::group_by(rows, |r| (r.task.as_str(), r.metric.as_str()));
    let headline = groups
        .keys()
        .find(|k| **k == ("depth", "rmse"))
        .or_else(|| groups.keys().next())
        .copied();
    let plots = groups.iter().flat_map(|(&(task, metric), points)| {
        // The band is the 95% interval (none with one seed).
        let curve = Curve::with_intervals(
            format!("calibrated − standard ({metric})"),
            [40, 90, 200],
            points.iter().map(|r| (r.fov_deg, r.mean, r.ci95)),
        );
        let n = points.iter().map(|r| r.n_seeds).min().unwrap_or(0);
        let spec = PlotSpec {
            title: format!("FT {task}: calibrated − standard {metric} vs field of view"),
            x_label: "field of view (deg)".into(),
            y_label: if n >= 2 {
                format!("{metric} difference (mean over {n} seeds, 95% t band)")
            } else {
                format!("{metric} difference ({n} seed: no interval)")
            },
            ..Default::default()
        };
        let own = format!("fov_gain_{task}_{metric}.png");
        // The headline pair is drawn a second time as `fov_gain.png`.
        let again = (headline == Some((task, metric))).then(|| {
            (
                "fov_gain.png".to_string(),
                spec.clone(),
                vec![curve.clone()],
            )
        });
        std::iter::once((own, spec, vec![curve])).chain(again)
    });
    super::write_rows_and_plots(rows, out, "fov_gain.json", plots)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::metrics::Metric;

    fn obs_with(sets: &[(&str, [f64; 3], [f64; 3])]) -> Observations {
        let mut obs = Observations::default();
        for (set, std_v, cal_v) in sets {
            for s in 0..3 {
                let c = Cell::new(Task::Depth, Block::Ft, set, STANDARD);
                obs.insert(&c, Metric::Rmse, s, std_v[s as usize]);
                obs.insert(
                    &c.with_kernel(CALIBRATED),
                    Metric::Rmse,
                    s,
                    cal_v[s as usize],
                );
            }
        }
        obs
    }

    #[test]
    fn the_gain_is_the_paired_difference_with_a_t_interval() {
        let obs = obs_with(&[
            ("F195", [1.0, 2.0, 3.0], [0.9, 1.8, 2.7]),
            ("F165", [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]),
        ]);
        let study = Study {
            study: None,
            replicates: Vec::new(),
            runs: Vec::new(),
            rows: Vec::new(),
        };
        // Without rows there is no camera file, so no field of view: no curve.
        assert!(fov_gain(&study, &obs).unwrap().is_empty());
        // The difference per seed is -0.1, -0.2, -0.3: mean -0.2, sd 0.1, t(0.975, 2) = 4.3027.
        let cell = Cell::new(Task::Depth, Block::Ft, "F195", CALIBRATED);
        let d = paired_difference(
            &obs.get(&cell, Metric::Rmse),
            &obs.get(&cell.with_kernel(STANDARD), Metric::Rmse),
        );
        let ci = MeanCi::of(&d.values().copied().collect::<Vec<_>>());
        assert!((ci.mean + 0.2).abs() < 1e-12);
        let h = ci.half_width.unwrap();
        assert!((h - 4.302653 * 0.1 / 3f64.sqrt()).abs() < 1e-5, "{h}");
    }

    #[test]
    fn plots_and_json_are_written_for_two_or_more_fields_of_view() {
        let rows: Vec<FovRow> = [(165.0, "F165", -0.01), (195.0, "F195", -0.05)]
            .into_iter()
            .map(|(fov_deg, set, mean)| FovRow {
                fov_deg,
                dataset: set.into(),
                task: "depth".into(),
                metric: "rmse".into(),
                mean,
                ci95: Some([mean - 0.02, mean + 0.02]),
                n_seeds: 3,
            })
            .collect();
        let dir = tempfile::tempdir().unwrap();
        let files = write_fov_gain(&rows, dir.path()).unwrap();
        for f in ["fov_gain.json", "fov_gain.png", "fov_gain_depth_rmse.png"] {
            assert!(dir.path().join(f).is_file(), "{f} missing: {files:?}");
        }
        let back: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join("fov_gain.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(back[1]["fov_deg"], 195.0);
        assert!((back[1]["ci95"][0].as_f64().unwrap() + 0.07).abs() < 1e-12);
        assert!(write_fov_gain(&[], dir.path()).unwrap().is_empty());
    }
}
