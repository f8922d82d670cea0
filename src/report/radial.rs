//! Radial plots of the report (paper Figs. 3 and 5): per task, block, calibration and metric,
//! the metric in rings around the principal point, one curve per kernel (standard red,
//! calibrated blue, rectified green). Distances are network-input pixels; the rectified images
//! are another (pinhole) projection, so their radius means another viewing angle.
//!
//! - With >= 2 seeds: each curve is the mean over seeds of the per-seed curves (the bin's value
//!   under the report's averaging), the band its 95% Student-t interval over seeds (per bin,
//!   over the seeds with a value there).
//! - With one seed: the paper's figure: the per-image mean of the metric in each bin, the band
//!   one standard deviation over the test images (a spread of images, not an interval).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::collect::{Row, Study};
use super::stats::MeanCi;
use super::study::{Block, Cell, Task, CALIBRATED, RECTIFIED};
use crate::error::Result;
use crate::eval::metrics::{Averaging, Metric};
use crate::plots::{
    line_band_plot, Curve, PlotSpec, CALIBRATED_BLUE, RECTIFIED_GREEN, STANDARD_RED,
};

/// Metrics with radial plots, per task.
pub fn radial_metrics(task: Task) -> [Metric; 2] {
    match task {
        Task::Depth => [Metric::Rmse, Metric::Delta1],
        Task::Segmentation => [Metric::MIoU, Metric::MAcc],
    }
}

fn colour(kernel: &str) -> [u8; 3] {
    match kernel {
        CALIBRATED => CALIBRATED_BLUE,
        RECTIFIED => RECTIFIED_GREEN,
        _ => STANDARD_RED,
    }
}

/// The curve of one cell over its rows (one per seed).
pub fn seed_curve(rows: &[&Row], m: Metric, averaging: Averaging) -> Option<Curve> {
    let first = rows.first()?;
    let x: Vec<f64> = first
        .record
        .radial
        .iter()
        .map(|b| (b.r_lo + b.r_hi) / 2.0)
        .collect();
    let (mut mean, mut band) = (Vec::new(), Vec::new());
    for (k, _) in x.iter().enumerate() {
        if rows.len() >= 2 {
            let v: Vec<f64> = rows
                .iter()
                .filter_map(|r| {
                    let b = r.record.radial.get(k)?;
                    b.value(m, averaging, r.record.is_depth())
                })
                .collect();
            let c = MeanCi::of(&v);
            mean.push(if v.is_empty() { f64::NAN } else { c.mean });
            band.push(c.half_width.unwrap_or(f64::NAN));
        } else {
            let b = &first.record.radial[k];
            mean.push(
                b.per_image_mean
                    .get(&m)
                    .copied()
                    .flatten()
                    .unwrap_or(f64::NAN),
            );
            band.push(
                b.per_image_std
                    .get(&m)
                    .copied()
                    .flatten()
                    .unwrap_or(f64::NAN),
            );
        }
    }
    Some(Curve {
        label: first.cell.kernel.clone(),
        colour: colour(&first.cell.kernel),
        x,
        mean,
        std: band,
    })
}

/// The radial plots of `task`: per block and fisheye data set with more than one kernel, per
/// metric, `radial_TASK_BLOCK_SET_METRIC.png` in `out`. Returns the files.
pub fn radial_plots(
    study: &Study,
    task: Task,
    averaging: Averaging,
    out: &Path,
) -> Result<Vec<PathBuf>> {
    let seeds = {
        let mut s: Vec<u64> = study.rows.iter().map(|r| r.seed).collect();
        s.sort();
        s.dedup();
        s.len()
    };
    let mut groups: BTreeMap<(Block, String), BTreeMap<Cell, Vec<&Row>>> = BTreeMap::new();
    for r in &study.rows {
        if r.cell.task == task && r.cell.dataset != "PERS" {
            groups
                .entry((r.cell.block, r.cell.dataset.clone()))
                .or_default()
                .entry(r.cell.clone())
                .or_default()
                .push(r);
        }
    }
    let mut files = Vec::new();
    for ((block, set), cells) in groups {
        if cells.len() < 2 {
            continue;
        }
        let mut cells: Vec<(Cell, Vec<&Row>)> = cells.into_iter().collect();
        cells.sort_by_key(|(c, _)| c.order());
        for m in radial_metrics(task) {
            let curves: Vec<Curve> = cells
                .iter()
                .filter_map(|(_, rows)| seed_curve(rows, m, averaging))
                .filter(|c| c.mean.iter().any(|v| v.is_finite()))
                .collect();
            if curves.is_empty() {
                continue;
            }
            let file = out.join(format!(
                "radial_{}_{}_{}_{m}.png",
                task.short(),
                block.to_string().to_lowercase(),
                set.to_lowercase()
            ));
            let y_label = if seeds >= 2 {
                format!("{m} (mean over {seeds} seeds, 95% t band)")
            } else {
                format!("{m} (1 seed: mean ± 1 std over images)")
            };
            let spec = PlotSpec {
                title: format!("{set}, {block}: {m} vs distance to the principal point"),
                x_label: "distance to the principal point (input px)".into(),
                y_label,
                size: [800, 500],
            };
            line_band_plot(&file, &spec, &curves)?;
            files.push(file);
        }
    }
    Ok(files)
}
