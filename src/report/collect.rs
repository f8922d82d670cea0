//! Reading a sweep's results folder for the report.
//!
//! ```text
//! RESULTS/seed-S/NAME/...   one replicate of the whole sweep per seed S (`--seeds 0,1,2`)
//! RESULTS/NAME/...          no `seed-*` folder: the folder is one replicate (its runs' seed)
//! ```
//!
//! A run directory is a folder with `experiment.toml` (see [`crate::experiment::run`]); its
//! evaluations are `eval/EVAL/metrics.json` ([`MetricsRecord`]) with `per_image.json`
//! ([`PerImageRecord`]) beside it. An evaluation named `SET-KERNEL` (`f195-calibrated`,
//! `f165-rectified`) is the row *data set* `SET`, *kernel* `KERNEL`; other names are rows of
//! their own (data set = the name, kernel = the evaluation's kernel). Runs without
//! `model.init` are the **BL** block, runs with one **FT**.
//!
//! Every file the report reads must parse: an unreadable `experiment.toml`, `metrics.json`,
//! `summary.json` or `sweep.json` is an error naming it (an absent `summary.json` or
//! `sweep.json` is a run trained outside a sweep: its times are blank).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::study::{Block, Cell, Observations, Task, KERNELS};
use super::tables::{paired_bootstrap, BootstrapIntervals};
use crate::error::{Error, Result};
use crate::eval::metrics::{Averaging, Metric, ALL_METRICS};
use crate::eval::record::{MetricsRecord, PerImageRecord};
use crate::experiment;
use crate::experiment::layout::{ResultsDir, RunDir, StudyRecord, Timing};

pub use crate::experiment::layout::Replicate;

/// The replicates of `results`: its `seed-S` folders by seed, else `results` itself
/// ([`ResultsDir::replicates`]).
pub fn replicates(results: &Path) -> Result<Vec<Replicate>> {
    ResultsDir::new(results).replicates()
}

/// One run directory.
#[derive(Clone, Debug)]
pub struct RunInfo {
    /// The replicate's seed (the run's own `seed` without seed folders).
    pub seed: u64,
    pub name: String,
    pub dir: PathBuf,
    pub task: Task,
    pub block: Block,
    /// The experiment text it ran with (`experiment.toml`).
    pub text: String,
    /// Training wall time and steps (`summary.json`), sweep wall time (`sweep.json`).
    pub train_seconds: Option<f64>,
    pub steps: Option<u64>,
    pub sweep_seconds: Option<f64>,
    /// When the sweep's action ended (Unix seconds): `sweep.json`'s `finished_unix`, or for
    /// records written before that field existed, the file's modification time (the sweep
    /// writes it as the run ends).
    pub sweep_finished: Option<f64>,
    /// Where the training call's time went (`summary.json`).
    pub timing: Option<Timing>,
    pub git: Option<String>,
    pub overrides: Vec<String>,
    pub profile: Option<String>,
}

/// One evaluation of one run.
#[derive(Clone, Debug)]
pub struct Row {
    pub seed: u64,
    pub run: String,
    pub cell: Cell,
    pub evaluation: String,
    pub record: MetricsRecord,
    /// `RUN/eval/NAME`.
    pub dir: PathBuf,
    /// The run's training set (folder and split) and the fraction of it the run trained on
    /// (`config.json`'s `train_data`; `None` where it does not say, e.g. the toy task).
    pub train_set: Option<TrainSet>,
}

/// A run's training set as `config.json` records it.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainSet {
    pub path: PathBuf,
    pub split: String,
    /// `None`: all of the split.
    pub fraction: Option<f64>,
}

impl TrainSet {
    /// The training set of the run in `run` (`None` if `config.json` is absent or names no
    /// data set folder).
    fn of(run: &RunDir) -> Result<Option<TrainSet>> {
        let file = run.config_json();
        let Ok(text) = std::fs::read_to_string(&file) else {
            return Ok(None);
        };
        let v: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Error::InvalidArgument(format!("{}: {e}", file.display())))?;
        let d = &v["train_data"]["dataset"];
        Ok(match (d["path"].as_str(), d["split"].as_str()) {
            (Some(path), Some(split)) => Some(TrainSet {
                path: PathBuf::from(path),
                split: split.to_string(),
                fraction: d["fraction"].as_f64(),
            }),
            _ => None,
        })
    }
}

/// Everything read from a results folder.
#[derive(Clone, Debug)]
pub struct Study {
    /// `RESULTS/study.json`, if a sweep wrote one (profile, seeds, shared baseline).
    pub study: Option<StudyRecord>,
    pub replicates: Vec<Replicate>,
    pub runs: Vec<RunInfo>,
    /// In table order, then by seed.
    pub rows: Vec<Row>,
}

/// The data set and kernel labels of an evaluation.
fn labels(name: &str, kernel: &str) -> (String, String) {
    for k in KERNELS {
        if let Some(set) = name.strip_suffix(k).and_then(|s| s.strip_suffix('-')) {
            if !set.is_empty() {
                return (set.to_uppercase(), k.to_string());
            }
        }
    }
    (name.to_string(), kernel.to_string())
}

fn read_run(run: &RunDir, seed: Option<u64>) -> Result<(RunInfo, Vec<Row>)> {
    let file = run.experiment_toml();
    let text = std::fs::read_to_string(&file).map_err(|e| Error::io(&file, e))?;
    let raw = experiment::parse(&text, &file)?;
    let task = Task::from(raw.task);
    let block = if raw.model.init.is_some() {
        Block::Ft
    } else {
        Block::Bl
    };
    let seed = seed.unwrap_or(raw.seed.unwrap_or(0));
    let summary = run.summary_if_any()?;
    let sweep = run.sweep_if_any()?;
    let record = run.run_if_any()?;
    let dir = run.path();
    let info = RunInfo {
        seed,
        name: raw.name.clone(),
        dir: dir.to_path_buf(),
        task,
        block,
        text: text.clone(),
        train_seconds: summary.as_ref().map(|s| s.seconds),
        timing: summary.as_ref().map(|s| s.timing.clone()),
        steps: summary.as_ref().map(|s| s.steps),
        sweep_seconds: sweep.as_ref().and_then(|s| s.seconds),
        sweep_finished: sweep
            .as_ref()
            .and_then(|s| s.finished_unix)
            .or_else(|| modified_unix(&run.sweep_json())),
        git: record.as_ref().and_then(|r| r.last_git().map(String::from)),
        overrides: sweep
            .as_ref()
            .map(|s| s.overlay.overrides.clone())
            .unwrap_or_default(),
        profile: sweep.and_then(|s| s.overlay.profile_name().map(String::from)),
    };
    let train_set = TrainSet::of(run)?;
    let mut rows = Vec::new();
    for name in run.evaluation_names()? {
        let e = run.eval_dir(&name);
        let record = MetricsRecord::read(&run.metrics_json(&name))?;
        let evaluation = record.about.evaluation.clone().unwrap_or(name);
        let (dataset, kernel) = labels(&evaluation, record.about.kernel.as_deref().unwrap_or(""));
        rows.push(Row {
            seed,
            run: raw.name.clone(),
            cell: Cell::new(task, block, &dataset, &kernel),
            evaluation,
            record,
            dir: e,
            train_set: train_set.clone(),
        });
    }
    Ok((info, rows))
}

/// Reads every run directory of every replicate of `results`.
pub fn collect(results: &Path) -> Result<Study> {
    let replicates = replicates(results)?;
    let (mut runs, mut rows) = (Vec::new(), Vec::new());
    for rep in &replicates {
        for run in ResultsDir::runs(rep)? {
            let (info, r) = read_run(&run, rep.seed)?;
            runs.push(info);
            rows.extend(r);
        }
    }
    rows.sort_by(|a, b| (a.cell.order(), a.seed, &a.run).cmp(&(b.cell.order(), b.seed, &b.run)));
    Ok(Study {
        study: ResultsDir::new(results).study_if_any()?,
        replicates,
        runs,
        rows,
    })
}

impl Study {
    /// The per-seed values of every metric of every row under `averaging`, and the radial
    /// curves of every metric. Two evaluations of one cell in one seed are an error (the
    /// table could not say which it shows).
    pub fn observations(&self, averaging: Averaging) -> Result<Observations> {
        let mut obs = Observations::default();
        let mut seen: BTreeMap<(Cell, u64), &Path> = BTreeMap::new();
        for r in &self.rows {
            if let Some(other) = seen.insert((r.cell.clone(), r.seed), &r.dir) {
                return Err(Error::InvalidArgument(format!(
                    "two evaluations are the row `{}` of seed {}: {} and {}",
                    r.cell,
                    r.seed,
                    other.display(),
                    r.dir.display()
                )));
            }
            let depth = r.record.is_depth();
            for m in ALL_METRICS {
                if let Some(v) = r.record.value(m, averaging) {
                    obs.insert(&r.cell, m, r.seed, v);
                }
                if m == Metric::Loss || r.record.radial.iter().all(|b| !b.pooled.contains_key(&m)) {
                    continue;
                }
                let curve: Vec<f64> = r
                    .record
                    .radial
                    .iter()
                    .map(|b| b.value(m, averaging, depth).unwrap_or(f64::NAN))
                    .collect();
                obs.radial
                    .entry((r.cell.clone(), m))
                    .or_default()
                    .insert(r.seed, curve);
            }
        }
        Ok(obs)
    }

    /// The row of `cell` in `seed`, if any.
    pub fn row(&self, cell: &Cell, seed: u64) -> Option<&Row> {
        self.rows.iter().find(|r| r.cell == *cell && r.seed == seed)
    }

    /// Per seed, the paired bootstrap intervals of every comparison in `pairs` (resampling
    /// seeded with `seed + replicate seed`), from each row's `per_image.json` (an error naming
    /// the file if it cannot be read).
    pub fn bootstrap(
        &self,
        pairs: &[(Cell, Cell)],
        averaging: Averaging,
        seed: u64,
    ) -> Result<BootstrapIntervals> {
        let mut out = BootstrapIntervals::new();
        let mut cache: BTreeMap<PathBuf, PerImageRecord> = BTreeMap::new();
        let mut load = |row: &Row| -> Result<PerImageRecord> {
            let path = row.dir.join(&row.record.per_image_file);
            if let Some(r) = cache.get(&path) {
                return Ok(r.clone());
            }
            let r = PerImageRecord::read(&path)?;
            cache.insert(path, r.clone());
            Ok(r)
        };
        let seeds: Vec<u64> = {
            let mut s: Vec<u64> = self.rows.iter().map(|r| r.seed).collect();
            s.sort();
            s.dedup();
            s
        };
        for (a, b) in pairs {
            for &s in &seeds {
                let (Some(ra), Some(rb)) = (self.row(a, s), self.row(b, s)) else {
                    continue;
                };
                let (pa, pb) = (load(ra)?, load(rb)?);
                let iv = paired_bootstrap(&pa, &pb, averaging, seed.wrapping_add(s));
                for (m, i) in iv.unwrap_or_default() {
                    out.entry((a.clone(), b.clone(), m))
                        .or_default()
                        .insert(s, i);
                }
            }
        }
        Ok(out)
    }

    /// Test images of the evaluations (the FT rows' count when they agree; otherwise the
    /// smallest count of any row).
    pub fn test_images(&self) -> u64 {
        let ft: Vec<u64> = self
            .rows
            .iter()
            .filter(|r| r.cell.block == Block::Ft)
            .map(|r| r.record.images)
            .collect();
        let all: Vec<u64> = self.rows.iter().map(|r| r.record.images).collect();
        match ft.first() {
            Some(&n) if ft.iter().all(|&x| x == n) => n,
            _ => all.into_iter().min().unwrap_or(0),
        }
    }

    /// The profile of the study (`study.json`), else those the runs were swept with (`none`
    /// if none; comma-separated if several).
    pub fn profile(&self) -> String {
        if let Some(s) = &self.study {
            return s.overlay.profile_name().unwrap_or("none").into();
        }
        let mut p: Vec<&str> = self
            .runs
            .iter()
            .map(|r| r.profile.as_deref().unwrap_or("none"))
            .collect();
        p.sort();
        p.dedup();
        if p.is_empty() {
            "none".into()
        } else {
            p.join(",")
        }
    }

    /// Whether one baseline served the fine-tunings of every seed (`study.json`).
    pub fn shared_baseline(&self) -> bool {
        self.study.as_ref().is_some_and(|s| s.share_baseline)
    }

    /// Elapsed wall seconds of the study: the length of the union of the intervals the runs
    /// occupied (`[finished - seconds, finished]` from `sweep.json`), so that runs that overlap
    /// (`--jobs 2`) count once and the pause before a resumed study goes on counts not at all. Runs without a time are left out (see [`Self::wall_seconds`] for their count).
    pub fn elapsed_seconds(&self) -> f64 {
        self.elapsed_seconds_of(|_| true)
    }

    /// [`Self::elapsed_seconds`] of the runs `keep` selects.
    pub fn elapsed_seconds_of(&self, keep: impl Fn(&RunInfo) -> bool) -> f64 {
        let spans = self.runs.iter().filter(|r| keep(r)).filter_map(|r| {
            let (s, end) = (r.sweep_seconds?, r.sweep_finished?);
            Some((end - s, end))
        });
        union_length(spans)
    }

    /// Whether `run` has an evaluation on one of `datasets` (cell data set names).
    pub fn evaluates_on(&self, run: &RunInfo, datasets: &[&str]) -> bool {
        self.rows.iter().any(|row| {
            row.seed == run.seed
                && row.run == run.name
                && datasets.contains(&row.cell.dataset.as_str())
        })
    }

    /// Sum of the runs' own sweep wall seconds (every seed; parallel runs overlap, so this is
    /// more than the elapsed time), and the runs without a time.
    pub fn wall_seconds(&self) -> (f64, usize) {
        let total = self.runs.iter().filter_map(|r| r.sweep_seconds).sum();
        let missing = self
            .runs
            .iter()
            .filter(|r| r.sweep_seconds.is_none())
            .count();
        (total, missing)
    }
}

/// A file's modification time in Unix seconds, if the file system tells.
fn modified_unix(path: &Path) -> Option<f64> {
    let t = std::fs::metadata(path).ok()?.modified().ok()?;
    Some(t.duration_since(std::time::UNIX_EPOCH).ok()?.as_secs_f64())
}

/// The total length of the union of intervals `(start, end)` (empty or reversed ones count 0).
pub fn union_length(spans: impl IntoIterator<Item = (f64, f64)>) -> f64 {
    let mut v: Vec<(f64, f64)> = spans.into_iter().filter(|(a, b)| b > a).collect();
    v.sort_by(|x, y| x.0.total_cmp(&y.0));
    let mut total = 0.0;
    let mut current: Option<(f64, f64)> = None;
    for (a, b) in v {
        current = match current {
            Some((ca, cb)) if a <= cb => Some((ca, cb.max(b))),
            Some((ca, cb)) => {
                total += cb - ca;
                Some((a, b))
            }
            None => Some((a, b)),
        };
    }
    total + current.map_or(0.0, |(a, b)| b - a)
}

#[cfg(test)]
mod union_tests {
    use super::union_length;

    #[test]
    fn overlapping_runs_count_once_and_gaps_not_at_all() {
        // Two parallel runs 0-10 and 5-12, then a resumed run later 100-103.
        let spans = [(0.0, 10.0), (100.0, 103.0), (5.0, 12.0)];
        assert_eq!(union_length(spans), 15.0);
        assert_eq!(union_length([(3.0, 3.0), (4.0, 2.0)]), 0.0);
        assert_eq!(union_length([(0.0, 4.0), (4.0, 6.0)]), 6.0);
    }
}
