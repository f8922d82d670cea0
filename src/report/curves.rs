//! Validation curves and per-run timings (`REPORT.md`'s "Training" section).
//!
//! - One plot per group of runs that differ only in their kernel (`NAME-standard`,
//!   `NAME-calibrated`, `NAME-rectified`; a baseline is a group of one): the validation metric
//!   the run selects its best checkpoint by (depth RMSE, segmentation mIoU) against the step,
//!   mean over seeds with a band of one standard deviation (`val_<group>.png`), and every
//!   value in `val_curves.csv`. For each curve the table gives the mean at the last logged step
//!   and its change over the last quarter of the steps: a baseline "trained until its
//!   validation curve flattens" shows a change near 0 there.
//! - `timings.csv`: per run its steps, training and sweep wall seconds and where the training
//!   time went ([`Timing`]); the section gives, per fine-tuning group, the sweep wall time of
//!   each kernel's run over the standard kernel's (same seed), mean over seeds.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::collect::{RunInfo, Study};
use super::stats::{mean, sample_sd};
use super::study::Task;
use crate::error::Result;
use crate::experiment::layout::{RunDir, Timing};
use crate::io::write_bytes_atomic;
use crate::plots::{
    line_band_plot, Curve, PlotSpec, CALIBRATED_BLUE, RECTIFIED_GREEN, STANDARD_RED,
};
use crate::train::csv::read_log;
use crate::util::fmt_f64;

/// The group of a run (its name without the kernel suffix) and its kernel label.
fn group_of(name: &str) -> (String, String) {
    for k in ["standard", "calibrated", "rectified"] {
        if let Some(g) = name.strip_suffix(&format!("-{k}")) {
            return (g.to_string(), k.to_string());
        }
    }
    (name.to_string(), "baseline".to_string())
}

fn colour(kernel: &str) -> [u8; 3] {
    match kernel {
        "calibrated" => CALIBRATED_BLUE,
        "rectified" => RECTIFIED_GREEN,
        "standard" => STANDARD_RED,
        _ => [60, 60, 60],
    }
}

/// The validation metric of a task's curves.
fn val_metric(task: Task) -> &'static str {
    match task {
        Task::Depth => "rmse",
        Task::Segmentation => "miou",
    }
}

/// Mean and sample standard deviation (0 for one value: no band).
fn mean_std(v: &[f64]) -> (f64, f64) {
    let sd = if v.len() < 2 { 0.0 } else { sample_sd(v) };
    (mean(v), sd)
}

/// One kernel's curve of a group: per step, the values of the seeds that logged it.
struct SeedCurves {
    kernel: String,
    by_step: BTreeMap<u64, Vec<f64>>,
}

impl SeedCurves {
    fn curve(&self) -> Curve {
        let (mut x, mut mean, mut std) = (Vec::new(), Vec::new(), Vec::new());
        for (step, v) in &self.by_step {
            let (m, s) = mean_std(v);
            x.push(*step as f64);
            mean.push(m);
            std.push(s);
        }
        Curve {
            label: self.kernel.clone(),
            colour: colour(&self.kernel),
            x,
            mean,
            std,
        }
    }

    /// The mean at the last step, and its change from the last step at or before 3/4 of it.
    fn flattening(&self) -> Option<(u64, f64, f64)> {
        let (&last, v) = self.by_step.iter().next_back()?;
        let end = mean_std(v).0;
        let (_, q) = self.by_step.range(..=last * 3 / 4).next_back()?;
        Some((last, end, end - mean_std(q).0))
    }
}

/// Writes the validation curves, `val_curves.csv` and `timings.csv`; returns the Markdown
/// section (empty if no run logged validation).
pub fn training_section(study: &Study, out: &Path, files: &mut Vec<PathBuf>) -> Result<String> {
    // group -> (task, kernel -> curves)
    let mut groups: BTreeMap<String, (Task, BTreeMap<String, SeedCurves>)> = BTreeMap::new();
    let mut csv = String::from("group,kernel,task,seed,step,metric,value\n");
    for r in &study.runs {
        let metric = val_metric(r.task);
        let Some(log) = read_log(&RunDir::new(&r.dir).val_csv())? else {
            continue;
        };
        let Some(values) = log.column(metric) else {
            continue;
        };
        let (group, kernel) = group_of(&r.name);
        let entry = groups
            .entry(group.clone())
            .or_insert_with(|| (r.task, BTreeMap::new()));
        let curves = entry.1.entry(kernel.clone()).or_insert_with(|| SeedCurves {
            kernel: kernel.clone(),
            by_step: BTreeMap::new(),
        });
        for (step, v) in values {
            curves.by_step.entry(step).or_default().push(v);
            csv += &format!(
                "{group},{kernel},{},{},{step},{metric},{}\n",
                r.task,
                r.seed,
                fmt_f64(v)
            );
        }
    }
    let mut md = String::new();
    if !groups.is_empty() {
        let file = out.join("val_curves.csv");
        write_bytes_atomic(&file, csv.as_bytes())?;
        files.push(file);
        md += "## Training\n\nValidation metric against the step (mean over seeds, band: one \
               standard deviation over seeds; every value in [val_curves.csv](val_curves.csv)). \
               \"Last quarter\" is the change of the mean from the last logged step at or before \
               3/4 of the run to its last step: near 0 when the curve has flattened.\n\n\
               | group | kernel | metric | seeds | steps | last | last quarter |\n\
               |---|---|---|---:|---:|---:|---:|\n";
        for (group, (task, kernels)) in &groups {
            let metric = val_metric(*task);
            for c in kernels.values() {
                let n = c.by_step.values().map(Vec::len).max().unwrap_or(0);
                if let Some((last, end, change)) = c.flattening() {
                    md += &format!(
                        "| {group} | {} | {metric} | {n} | {last} | {end:.4} | {change:+.4} \
                         ({:+.1}%) |\n",
                        c.kernel,
                        100.0 * change / end
                    );
                }
            }
            let curves: Vec<Curve> = kernels.values().map(SeedCurves::curve).collect();
            let file = out.join(format!("val_{group}.png"));
            let spec = PlotSpec {
                title: format!("{group}: validation {metric}"),
                x_label: "step".into(),
                y_label: metric.into(),
                size: [640, 400],
            };
            line_band_plot(&file, &spec, &curves)?;
            files.push(file);
        }
        md += "\n";
        for group in groups.keys() {
            md += &format!("![{group}](val_{group}.png)\n");
        }
        md += "\n";
    }
    md += &timings(study, out, files)?;
    Ok(md)
}

/// `timings.csv` and the kernels' wall-time ratios per fine-tuning group.
fn timings(study: &Study, out: &Path, files: &mut Vec<PathBuf>) -> Result<String> {
    let mut csv = String::from(
        "seed,name,task,block,steps,train_s,sweep_s,build_s,data_s,steps_s,validation_s,\
         checkpoints_s,evaluation_s\n",
    );
    let opt = |v: Option<f64>| v.map(fmt_f64).unwrap_or_default();
    for r in &study.runs {
        let t = r.timing.clone().unwrap_or_default();
        let has = r.timing.is_some();
        let part = |v: f64| if has { fmt_f64(v) } else { String::new() };
        csv += &format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            r.seed,
            r.name,
            r.task,
            r.block,
            r.steps.map(|s| s.to_string()).unwrap_or_default(),
            opt(r.train_seconds),
            opt(r.sweep_seconds),
            part(t.build),
            part(t.data),
            part(t.steps),
            part(t.validation),
            part(t.checkpoints),
            opt(t.evaluation),
        );
    }
    let file = out.join("timings.csv");
    write_bytes_atomic(&file, csv.as_bytes())?;
    files.push(file);
    let ratios = kernel_ratios(&study.runs);
    if ratios.is_empty() {
        return Ok("Per-run timings: [timings.csv](timings.csv).\n\n".into());
    }
    let mut md = String::from(
        "Per-run timings: [timings.csv](timings.csv). Sweep wall time of each kernel's \
         fine-tuning over the standard kernel's (same seed; training, validation and \
         evaluations), mean over seeds, and the training steps alone:\n\n\
         | group | kernel | seeds | wall / standard | steps / standard |\n|---|---|---:|---:|---:|\n",
    );
    for ((group, kernel), (n, wall, steps)) in ratios {
        md += &format!("| {group} | {kernel} | {n} | {wall:.2}x | {steps:.2}x |\n");
    }
    Ok(md + "\n")
}

/// Per (group, non-standard kernel): seeds, mean sweep-time ratio and mean step-time ratio
/// against the same seed's standard run.
fn kernel_ratios(runs: &[RunInfo]) -> BTreeMap<(String, String), (usize, f64, f64)> {
    let mut standard: BTreeMap<(String, u64), &RunInfo> = BTreeMap::new();
    for r in runs {
        let (g, k) = group_of(&r.name);
        if k == "standard" {
            standard.insert((g, r.seed), r);
        }
    }
    let steps_s = |r: &RunInfo| r.timing.as_ref().map(|t: &Timing| t.steps);
    let mut acc: BTreeMap<(String, String), Vec<(f64, f64)>> = BTreeMap::new();
    for r in runs {
        let (g, k) = group_of(&r.name);
        if k == "standard" || k == "baseline" {
            continue;
        }
        let Some(s) = standard.get(&(g.clone(), r.seed)) else {
            continue;
        };
        if let (Some(a), Some(b), Some(sa), Some(sb)) =
            (r.sweep_seconds, s.sweep_seconds, steps_s(r), steps_s(s))
        {
            acc.entry((g, k)).or_default().push((a / b, sa / sb));
        }
    }
    acc.into_iter()
        .map(|(key, v)| {
            let (wall, steps): (Vec<f64>, Vec<f64>) = v.into_iter().unzip();
            (key, (wall.len(), mean(&wall), mean(&steps)))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_strip_the_kernel_suffix() {
        assert_eq!(
            group_of("paper-depth-ft-f195-calibrated"),
            ("paper-depth-ft-f195".into(), "calibrated".into())
        );
        assert_eq!(
            group_of("paper-seg-bl-pers"),
            ("paper-seg-bl-pers".into(), "baseline".into())
        );
    }

    #[test]
    fn flattening_compares_the_last_step_with_three_quarters() {
        let mut by_step = BTreeMap::new();
        for (s, v) in [(100, [2.0, 2.2]), (300, [1.2, 1.4]), (400, [1.0, 1.2])] {
            by_step.insert(s, v.to_vec());
        }
        let c = SeedCurves {
            kernel: "baseline".into(),
            by_step,
        };
        let (last, end, change) = c.flattening().unwrap();
        assert_eq!(last, 400);
        assert!((end - 1.1).abs() < 1e-12);
        assert!((change - (1.1 - 1.3)).abs() < 1e-12, "{change}");
        let curve = c.curve();
        assert_eq!(curve.x, [100.0, 300.0, 400.0]);
        assert!((curve.std[0] - 0.02f64.sqrt()).abs() < 1e-9);
    }
}
