//! The report's tables from [`Observations`]: the paper's Tables 1 and 2 with every cell the
//! mean over seeds ± the 95% Student-t half-width (and `n`), and the paired-difference table
//! (calibrated − standard, rectified − standard per task, block, calibration and metric) with
//! the mean and 95% t-interval over seeds and, per seed, a paired bootstrap interval over the
//! test images ([`paired_bootstrap`]).
//!
//! With one seed no interval is printed: cells are the one value and the tables say that
//! intervals need >= 2 seeds. (A bootstrap over test images alone would leave out the
//! seed-to-seed spread, which the issue measured larger than the paper's effect.)

use std::collections::BTreeMap;

use super::stats::{bootstrap, MeanCi};
use super::study::{
    paired_difference, Block, Cell, Observations, Task, CALIBRATED, CALIBRATED_LEARNED, CAMCONV,
    RECTIFIED, STANDARD,
};
use crate::eval::metrics::{Averaging, Metric};
use crate::eval::record::PerImageRecord;

/// Resamples of the bootstrap over test images (the issue asks for >= 1000).
pub const BOOTSTRAP_RESAMPLES: usize = 2000;

/// The comparisons of the difference table: (minuend kernel, subtrahend kernel).
pub const COMPARISONS: [(&str, &str); 4] = [
    (CALIBRATED, STANDARD),
    (RECTIFIED, STANDARD),
    (CAMCONV, STANDARD),
    (CALIBRATED_LEARNED, STANDARD),
];

/// Per seed, per (minuend cell, subtrahend cell, metric): the bootstrap interval over test
/// images (`None`: not computable, e.g. no shared sample ids).
pub type BootstrapIntervals = BTreeMap<(Cell, Cell, Metric), BTreeMap<u64, Option<[f64; 2]>>>;

/// `mean ± h` (4 decimals), or the value alone without an interval.
pub fn fmt_ci(c: &MeanCi) -> String {
    match c.half_width {
        Some(h) => format!("{:.4} ± {h:.4}", c.mean),
        None => format!("{:.4}", c.mean),
    }
}

fn fmt_interval(iv: Option<[f64; 2]>) -> String {
    iv.map(|[a, b]| format!("[{a:+.4}, {b:+.4}]"))
        .unwrap_or_else(|| "–".into())
}

/// The sentence under a table's title saying what its numbers are.
pub fn convention(task: Task, averaging: Averaging, seeds: usize) -> String {
    let avg = match task {
        Task::Depth => format!(
            "depth metrics `{averaging}` ({})",
            match averaging {
                Averaging::PerImage => {
                    "each metric per test image over its valid pixels, then the mean over images: \
                     the authors' convention"
                }
                Averaging::Pooled => "each metric over all valid pixels of the test set",
            }
        ),
        Task::Segmentation => {
            "mIoU / mAcc / pixel accuracy from one confusion matrix over the test set".to_string()
        }
    };
    let stat = if seeds >= 2 {
        format!(
            "each cell the mean over seeds ± the 95% half-width (Student t, n - 1 degrees of \
             freedom), n = seeds in column `n` ({seeds} in the study)"
        )
    } else {
        "one seed: each cell is that seed's value; intervals need >= 2 seeds \
         (`calibconv sweep ... --seeds 0,1,2`)"
            .to_string()
    };
    format!("{avg}; {stat}; ↓ lower is better, ↑ higher is better; bold: the best mean per block and calibration")
}

/// The Markdown and CSV table of `task`'s cells with `columns`.
pub fn cell_table(obs: &Observations, task: Task, columns: &[Metric]) -> (String, String) {
    let arrow = |m: &Metric| if m.higher_is_better() { "↑" } else { "↓" };
    let mut md = format!(
        "| Training | Data set | Kernel | n | {} |\n|---|---|---|---:|{}\n",
        columns
            .iter()
            .map(|c| format!("{c} {}", arrow(c)))
            .collect::<Vec<_>>()
            .join(" | "),
        "---:|".repeat(columns.len())
    );
    let mut csv = format!(
        "block,dataset,kernel,n,{}\n",
        columns
            .iter()
            .map(|c| format!("{c},{c}_ci95_half_width"))
            .collect::<Vec<_>>()
            .join(",")
    );
    let cells: Vec<Cell> = obs.cells().into_iter().filter(|c| c.task == task).collect();
    let stat = |c: &Cell, m: Metric| {
        let v: Vec<f64> = obs.get(c, m).into_values().collect();
        (!v.is_empty()).then(|| MeanCi::of(&v))
    };
    for cell in &cells {
        let peers: Vec<&Cell> = cells
            .iter()
            .filter(|o| o.block == cell.block && o.dataset == cell.dataset)
            .collect();
        let n = columns
            .iter()
            .map(|m| obs.get(cell, *m).len())
            .max()
            .unwrap_or(0);
        let mut md_cells = Vec::new();
        let mut csv_cells = Vec::new();
        for &m in columns {
            match stat(cell, m) {
                None => {
                    md_cells.push("–".to_string());
                    csv_cells.push(",".to_string());
                }
                Some(c) => {
                    let best = peers.len() > 1
                        && peers.iter().all(|o| {
                            let w = stat(o, m).map(|s| s.mean).unwrap_or(f64::NAN);
                            !w.is_finite()
                                || if m.higher_is_better() {
                                    c.mean >= w
                                } else {
                                    c.mean <= w
                                }
                        });
                    let text = fmt_ci(&c);
                    md_cells.push(if best { format!("**{text}**") } else { text });
                    csv_cells.push(format!(
                        "{},{}",
                        c.mean,
                        c.half_width.map(|h| h.to_string()).unwrap_or_default()
                    ));
                }
            }
        }
        let block = match cell.block {
            Block::Bl => "BL (Pers)",
            Block::Ft => "FT",
        };
        md += &format!(
            "| {block} | {} | {} | {n} | {} |\n",
            cell.dataset,
            cell.kernel,
            md_cells.join(" | ")
        );
        csv += &format!(
            "{},{},{},{n},{}\n",
            cell.block,
            cell.dataset,
            cell.kernel,
            csv_cells.join(",")
        );
    }
    (md, csv)
}

/// Every observed value of `task`'s cells, one line per (cell, seed, metric):
/// `block,dataset,kernel,seed,metric,value` (what the table's means and intervals are made of).
pub fn seed_values_csv(obs: &Observations, task: Task, columns: &[Metric]) -> String {
    let mut csv = String::from("block,dataset,kernel,seed,metric,value\n");
    for cell in obs.cells().into_iter().filter(|c| c.task == task) {
        for &m in columns {
            for (s, v) in obs.get(&cell, m) {
                csv += &format!(
                    "{},{},{},{s},{m},{v}\n",
                    cell.block, cell.dataset, cell.kernel
                );
            }
        }
    }
    csv
}

/// The (minuend, subtrahend) cell pairs of `task` that the difference table compares: per
/// block and data set, each of [`COMPARISONS`] whose two rows were observed.
pub fn comparison_pairs(obs: &Observations, task: Task) -> Vec<(Cell, Cell)> {
    let cells: Vec<Cell> = obs.cells().into_iter().filter(|c| c.task == task).collect();
    let mut pairs = Vec::new();
    for c in &cells {
        for (a, b) in COMPARISONS {
            if c.kernel == b {
                let other = c.with_kernel(a);
                if cells.contains(&other) {
                    pairs.push((other, c.clone()));
                }
            }
        }
    }
    pairs.sort_by_key(|(a, _)| a.order());
    pairs
}

/// The Markdown and CSV difference table of `task`.
pub fn difference_table(
    obs: &Observations,
    boot: &BootstrapIntervals,
    task: Task,
    columns: &[Metric],
) -> (String, String) {
    let seeds = obs.seeds().len();
    let mut md = format!(
        "| Training | Data set | Difference | Metric | n | Mean | 95% CI over seeds | Per seed: \
         difference{} |\n|---|---|---|---|---:|---:|---|---|\n",
        if seeds >= 2 {
            " [95% paired bootstrap over test images]"
        } else {
            ""
        }
    );
    let mut csv = String::from(
        "block,dataset,minuend,subtrahend,metric,n,mean,ci95_lo,ci95_hi,seed,seed_difference,\
         bootstrap_lo,bootstrap_hi\n",
    );
    for (a, b) in comparison_pairs(obs, task) {
        for &m in columns {
            let d = paired_difference(&obs.get(&a, m), &obs.get(&b, m));
            if d.is_empty() {
                continue;
            }
            let values: Vec<f64> = d.values().copied().collect();
            let ci = MeanCi::of(&values);
            let iv = (seeds >= 2).then(|| ci.interval()).flatten();
            let per_boot = boot.get(&(a.clone(), b.clone(), m));
            let per_seed: Vec<String> = d
                .iter()
                .map(|(s, x)| {
                    let bi = per_boot.and_then(|p| p.get(s).copied().flatten());
                    if seeds >= 2 {
                        format!("s{s}: {x:+.4} {}", fmt_interval(bi))
                    } else {
                        format!("s{s}: {x:+.4}")
                    }
                })
                .collect();
            let (block, set, ka, kb) = (&a.block, &a.dataset, &a.kernel, &b.kernel);
            let (n, mean) = (ci.n, ci.mean);
            md += &format!(
                "| {block} | {set} | {ka} − {kb} | {m} | {n} | {mean:+.4} | {} | {} |\n",
                if seeds >= 2 {
                    fmt_interval(iv)
                } else {
                    "needs >= 2 seeds".into()
                },
                per_seed.join("; ")
            );
            for (s, x) in &d {
                let bi = per_boot
                    .and_then(|p| p.get(s).copied().flatten())
                    .filter(|_| seeds >= 2);
                let opt = |v: Option<f64>| v.map(|x| x.to_string()).unwrap_or_default();
                csv += &format!(
                    "{block},{set},{ka},{kb},{m},{n},{mean},{},{},{s},{x},{},{}\n",
                    opt(iv.map(|i| i[0])),
                    opt(iv.map(|i| i[1])),
                    opt(bi.map(|i| i[0])),
                    opt(bi.map(|i| i[1])),
                );
            }
        }
    }
    (md, csv)
}

/// Percentile intervals (95%, [`BOOTSTRAP_RESAMPLES`] resamples, seeded with `seed`) of the
/// difference `a - b` of every metric of the two evaluations, paired by sample id: each
/// resample draws test images with replacement and recomputes both rows' set metrics on the
/// same images (as [`PerImageRecord::aggregate`] computes them). `None` without shared ids.
pub fn paired_bootstrap(
    a: &PerImageRecord,
    b: &PerImageRecord,
    averaging: Averaging,
    seed: u64,
) -> Option<Vec<(Metric, Option<[f64; 2]>)>> {
    let index: BTreeMap<&str, usize> = b
        .samples
        .iter()
        .enumerate()
        .map(|(i, s)| (s.id.as_str(), i))
        .collect();
    let (ia, ib): (Vec<usize>, Vec<usize>) = a
        .samples
        .iter()
        .enumerate()
        .filter_map(|(i, s)| index.get(s.id.as_str()).map(|&j| (i, j)))
        .unzip();
    if ia.is_empty() || a.header.task != b.header.task {
        return None;
    }
    let metrics: Vec<Metric> = a.aggregate(&ia, averaging).iter().map(|p| p.0).collect();
    let (mut ra, mut rb) = (vec![0; ia.len()], vec![0; ib.len()]);
    let iv = bootstrap(
        ia.len(),
        metrics.len(),
        BOOTSTRAP_RESAMPLES,
        seed,
        0.95,
        |idx| {
            for (k, &i) in idx.iter().enumerate() {
                ra[k] = ia[i];
                rb[k] = ib[i];
            }
            let (x, y) = (a.aggregate(&ra, averaging), b.aggregate(&rb, averaging));
            x.iter().zip(&y).map(|(p, q)| p.1 - q.1).collect()
        },
    );
    Some(metrics.into_iter().zip(iv).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::metrics::DepthSums;
    use crate::eval::record::{metric_map, RecordHeader, SampleRecord};

    fn obs(seeds: &[(f64, f64)]) -> Observations {
        let mut o = Observations::default();
        let std = Cell::new(Task::Depth, Block::Ft, "F195", STANDARD);
        let cal = std.with_kernel(CALIBRATED);
        for (s, (x, y)) in seeds.iter().enumerate() {
            o.insert(&std, Metric::Rmse, s as u64, *x);
            o.insert(&cal, Metric::Rmse, s as u64, *y);
        }
        o
    }

    #[test]
    fn cells_carry_mean_half_width_and_n() {
        let o = obs(&[(1.0, 0.9), (2.0, 1.0), (3.0, 1.1)]);
        let (md, csv) = cell_table(&o, Task::Depth, &[Metric::Rmse]);
        // standard: 1, 2, 3 -> 2 ± 4.3027 / sqrt 3 = 2.4841; calibrated 1 ± 0.2484 (bold).
        assert!(
            md.contains("| FT | F195 | standard | 3 | 2.0000 ± 2.4841 |"),
            "{md}"
        );
        assert!(
            md.contains("| FT | F195 | calibrated | 3 | **1.0000 ± 0.2484** |"),
            "{md}"
        );
        assert!(
            csv.starts_with(
                "block,dataset,kernel,n,rmse,rmse_ci95_half_width\nFT,F195,standard,3,2,2.484"
            ),
            "{csv}"
        );
        // One seed: values alone.
        let o = obs(&[(1.0, 0.9)]);
        let (md, _) = cell_table(&o, Task::Depth, &[Metric::Rmse]);
        assert!(md.contains("| FT | F195 | standard | 1 | 1.0000 |"), "{md}");
        assert!(convention(Task::Depth, Averaging::PerImage, 1).contains("need >= 2 seeds"));
        let o = obs(&[(1.0, 0.9), (2.0, 1.0)]);
        let csv = seed_values_csv(&o, Task::Depth, &[Metric::Rmse]);
        assert_eq!(
            csv,
            "block,dataset,kernel,seed,metric,value\nFT,F195,standard,0,rmse,1\n\
             FT,F195,standard,1,rmse,2\nFT,F195,calibrated,0,rmse,0.9\nFT,F195,calibrated,1,rmse,1\n"
        );
        assert!(convention(Task::Depth, Averaging::PerImage, 3).contains("`per-image`"));
    }

    #[test]
    fn differences_are_paired_by_seed() {
        // Differences -0.1, -1.0, -1.9: paired, not the difference of means of unpaired rows.
        let o = obs(&[(1.0, 0.9), (2.0, 1.0), (3.0, 1.1)]);
        let mut boot = BootstrapIntervals::new();
        let (std, cal) = (
            Cell::new(Task::Depth, Block::Ft, "F195", STANDARD),
            Cell::new(Task::Depth, Block::Ft, "F195", CALIBRATED),
        );
        boot.entry((cal.clone(), std.clone(), Metric::Rmse))
            .or_default()
            .insert(0, Some([-0.2, 0.0]));
        assert_eq!(comparison_pairs(&o, Task::Depth), vec![(cal, std)]);
        let (md, csv) = difference_table(&o, &boot, Task::Depth, &[Metric::Rmse]);
        assert!(
            md.contains("| FT | F195 | calibrated − standard | rmse | 3 | -1.0000 |"),
            "{md}"
        );
        assert!(
            md.contains("s0: -0.1000 [-0.2000, +0.0000]; s1: -1.0000 –"),
            "{md}"
        );
        assert_eq!(csv.lines().count(), 4);
        let o = obs(&[(1.0, 0.9)]);
        let (md, _) = difference_table(&o, &boot, Task::Depth, &[Metric::Rmse]);
        assert!(md.contains("needs >= 2 seeds") && !md.contains('['), "{md}");
    }

    fn depth_record(ids: &[&str], errors: &[f64]) -> PerImageRecord {
        // One pixel per image, ground truth 1, prediction 1 + e.
        let samples = ids
            .iter()
            .zip(errors)
            .map(|(id, e)| {
                let sums = DepthSums {
                    count: 1.0,
                    abs_rel: e.abs(),
                    abs: e.abs(),
                    sq: e * e,
                    sq_log: (1.0 + e).ln().powi(2),
                    delta: [1.0; 3],
                };
                SampleRecord {
                    id: id.to_string(),
                    pixels: 1,
                    metrics: metric_map([]),
                    depth_sums: Some(sums),
                    class_counts: None,
                }
            })
            .collect();
        PerImageRecord {
            header: RecordHeader {
                format: "calibconv-per-image".into(),
                version: 2,
                task: "depth".into(),
            },
            classes: vec![],
            samples,
        }
    }

    #[test]
    fn bootstrap_pairs_by_sample_id() {
        // b is a in another order with every error 0.1 larger: the paired MAE difference is
        // exactly -0.1 in every resample, so the interval has zero width. Unpaired resampling
        // would spread it by the images' spread (errors 0..1).
        let ids = ["a", "b", "c", "d", "e"];
        let ea = [0.0, 0.25, 0.5, 0.75, 1.0];
        let a = depth_record(&ids, &ea);
        let rev: Vec<&str> = ids.iter().rev().copied().collect();
        let eb: Vec<f64> = ea.iter().rev().map(|e| e + 0.1).collect();
        let b = depth_record(&rev, &eb);
        let iv = paired_bootstrap(&a, &b, Averaging::PerImage, 3).unwrap();
        let (m, mae) = iv[1];
        assert_eq!(m, Metric::Mae);
        let [lo, hi] = mae.unwrap();
        assert!(
            (lo + 0.1).abs() < 1e-12 && (hi + 0.1).abs() < 1e-12,
            "{lo} {hi}"
        );
        // The same seed gives the same intervals; no shared ids gives none.
        assert_eq!(
            paired_bootstrap(&a, &b, Averaging::PerImage, 3).unwrap(),
            iv
        );
        let c = depth_record(&["x"], &[0.0]);
        assert!(paired_bootstrap(&a, &c, Averaging::Pooled, 3).is_none());
    }
}
