//! The run-directory format: every path of a run directory and of a sweep's results folder, and
//! the records written in them as serde types. Writers (training, evaluation, sweeps) and
//! readers (sweep state, the report) go through this module, so a file name or a key exists
//! once; a record that a reader needs and cannot read is an [`Error::Record`] naming the file.
//!
//! ```text
//! RESULTS/                      a sweep's output folder (the profile's `output`)
//!   study.json                  the last sweep over it: profile, seeds, runs  (StudyRecord)
//!   seed-S/NAME/                run NAME of replicate seed S (a sweep with seeds); without
//!                               seeds the run directories are RESULTS/NAME/ (one replicate,
//!                               the experiment's own seed)
//! RUN = OUTPUT/NAME/
//!   lock                        held (flock) while a process trains or evaluates the run; holds
//!                               the holder's PID (see RunLock)
//!   experiment.toml             the experiment file as given (the last invocation's)
//!   config.json                 the resolved experiment: every default, absolute paths
//!   run.json                    one record per invocation, one segment per process that
//!                               trained it (RunRecord)
//!   summary.json                what the last training call did, with a timing breakdown
//!                               (Summary)
//!   sweep.json                  the sweep that ran it: profile, overrides, outcome
//!                               (SweepRecord)
//!   checkpoints/                last.safetensors, last.optim.safetensors, best.safetensors
//!   train.csv  val.csv          training and validation scalars by step
//!   tb/                         TensorBoard event files
//!   eval/EVAL/                  metrics.json (written by crate::eval), metrics.csv,
//!                               radial.csv, radial_METRIC.png, predictions/*.png
//!   evaluations.csv             one row per evaluation in eval/
//! ```

use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::io::write_bytes_atomic;
use crate::train::{best_path, last_path};

pub use super::lock::RunLock;

const STUDY_JSON: &str = "study.json";
const METRICS_JSON: &str = "metrics.json";
/// Prefix of a replicate folder: `seed-S`.
const SEED_PREFIX: &str = "seed-";

/// The files and folders directly in a run directory, one `RunDir` getter each: the table
/// below is where their names are written.
macro_rules! run_dir_entries {
    ($($(#[$doc:meta])* $getter:ident => $name:literal,)*) => {
        impl RunDir {
            $(
                $(#[$doc])*
                pub fn $getter(&self) -> PathBuf {
                    self.root.join($name)
                }
            )*
        }
    };
}

run_dir_entries! {
    /// `experiment.toml`: the merged experiment text it ran with.
    experiment_toml => "experiment.toml",
    /// `config.json`: the resolved experiment.
    config_json => "config.json",
    /// `run.json`: [`RunRecord`].
    run_json => "run.json",
    /// `summary.json`: [`Summary`].
    summary_json => "summary.json",
    /// `sweep.json`: [`SweepRecord`].
    sweep_json => "sweep.json",
    /// `lock`: see [`RunLock`].
    lock_file => "lock",
    /// `checkpoints/`.
    checkpoints => "checkpoints",
    /// `eval/`.
    eval_root => "eval",
    /// `evaluations.csv`.
    evaluations_csv => "evaluations.csv",
    /// `train.csv` (written by [`crate::train::csv::CsvLog`]).
    train_csv => "train.csv",
    /// `val.csv` (written by [`crate::train::csv::CsvLog`]).
    val_csv => "val.csv",
    /// `tb/`: TensorBoard event files.
    tb => "tb",
}

/// A run directory, `OUTPUT/NAME`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RunDir {
    root: PathBuf,
}

impl RunDir {
    /// The run directory at `root` (nothing is created).
    pub fn new(root: impl Into<PathBuf>) -> Self {
        RunDir { root: root.into() }
    }

    /// The folder itself.
    pub fn path(&self) -> &Path {
        &self.root
    }

    /// The run's name (the folder's name).
    pub fn name(&self) -> String {
        self.root
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    }

    /// Whether it holds a run (its `experiment.toml` exists).
    pub fn exists(&self) -> bool {
        self.experiment_toml().is_file()
    }

    /// `checkpoints/last.safetensors`.
    pub fn last_checkpoint(&self) -> PathBuf {
        last_path(&self.checkpoints())
    }
    /// `checkpoints/best.safetensors`.
    pub fn best_checkpoint(&self) -> PathBuf {
        best_path(&self.checkpoints())
    }
    /// `eval/NAME/`.
    pub fn eval_dir(&self, name: &str) -> PathBuf {
        self.eval_root().join(name)
    }
    /// `eval/NAME/metrics.json` (its record is [`crate::eval`]'s).
    pub fn metrics_json(&self, name: &str) -> PathBuf {
        metrics_json(&self.eval_dir(name))
    }

    /// The names of the evaluations in `eval/` that have a `metrics.json`, sorted.
    pub fn evaluation_names(&self) -> Result<Vec<String>> {
        let root = self.eval_root();
        let entries = match std::fs::read_dir(&root) {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(Error::io(&root, e)),
        };
        let mut names = Vec::new();
        for entry in entries {
            let entry = entry.map_err(|e| Error::io(&root, e))?;
            if metrics_json(&entry.path()).is_file() {
                names.push(entry.file_name().to_string_lossy().into_owned());
            }
        }
        names.sort();
        Ok(names)
    }

    /// Reads `summary.json`.
    pub fn read_summary(&self) -> Result<Summary> {
        read_record(&self.summary_json())
    }
    /// Reads `sweep.json`.
    pub fn read_sweep(&self) -> Result<SweepRecord> {
        read_record(&self.sweep_json())
    }
    /// Reads `run.json`.
    pub fn read_run(&self) -> Result<RunRecord> {
        read_record(&self.run_json())
    }
    /// Reads `summary.json` if it exists (an unreadable one is an error).
    pub fn summary_if_any(&self) -> Result<Option<Summary>> {
        read_optional(&self.summary_json())
    }
    /// Reads `sweep.json` if it exists (an unreadable one is an error).
    pub fn sweep_if_any(&self) -> Result<Option<SweepRecord>> {
        read_optional(&self.sweep_json())
    }
    /// Reads `run.json` if it exists (an unreadable one is an error).
    pub fn run_if_any(&self) -> Result<Option<RunRecord>> {
        read_optional(&self.run_json())
    }

    /// Takes the run's lock (creating the folder): see [`RunLock`].
    pub fn lock(&self) -> Result<RunLock> {
        RunLock::acquire(self)
    }
}

/// `DIR/metrics.json` of an evaluation folder.
pub fn metrics_json(eval_dir: &Path) -> PathBuf {
    eval_dir.join(METRICS_JSON)
}

/// A results folder: the `output` of a sweep, holding run directories directly (one
/// replicate) or replicate folders `seed-S/` that hold them.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ResultsDir {
    root: PathBuf,
}

/// One replicate of a results folder.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Replicate {
    /// The seed of a `seed-S/` folder; `None` for a results folder without them (its runs ran
    /// with their experiments' own seeds).
    pub seed: Option<u64>,
    /// The folder holding its run directories.
    pub dir: PathBuf,
}

impl ResultsDir {
    /// The results folder at `root`.
    pub fn new(root: impl Into<PathBuf>) -> Self {
        ResultsDir { root: root.into() }
    }
    /// The folder itself.
    pub fn path(&self) -> &Path {
        &self.root
    }
    /// `study.json`: [`StudyRecord`].
    pub fn study_json(&self) -> PathBuf {
        self.root.join(STUDY_JSON)
    }
    /// `seed-S/`: the replicate folder of seed `seed`.
    pub fn seed_dir(&self, seed: u64) -> PathBuf {
        self.root.join(seed_folder(seed))
    }
    /// The run directory of `name` in replicate `seed` (`seed-S/NAME`, or `NAME` for `None`).
    pub fn run_dir(&self, seed: Option<u64>, name: &str) -> RunDir {
        match seed {
            Some(s) => RunDir::new(self.seed_dir(s).join(name)),
            None => RunDir::new(self.root.join(name)),
        }
    }

    /// The replicates, by seed: every `seed-S/` folder, or the folder itself (seed `None`)
    /// when it has none.
    pub fn replicates(&self) -> Result<Vec<Replicate>> {
        let mut out = Vec::new();
        for entry in std::fs::read_dir(&self.root).map_err(|e| Error::io(&self.root, e))? {
            let entry = entry.map_err(|e| Error::io(&self.root, e))?;
            let path = entry.path();
            if !path.is_dir() {
                continue;
            }
            if let Some(seed) = parse_seed_folder(&entry.file_name().to_string_lossy()) {
                out.push(Replicate {
                    seed: Some(seed),
                    dir: path,
                });
            }
        }
        if out.is_empty() {
            out.push(Replicate {
                seed: None,
                dir: self.root.clone(),
            });
        }
        out.sort_by_key(|r| r.seed);
        Ok(out)
    }

    /// The run directories of one replicate (folders with `experiment.toml`), sorted by name.
    pub fn runs(replicate: &Replicate) -> Result<Vec<RunDir>> {
        let dir = &replicate.dir;
        let mut out = Vec::new();
        for entry in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
            let entry = entry.map_err(|e| Error::io(dir, e))?;
            let run = RunDir::new(entry.path());
            if run.exists() {
                out.push(run);
            }
        }
        out.sort_by(|a, b| a.root.cmp(&b.root));
        Ok(out)
    }

    /// Reads `study.json` if it exists (an unreadable one is an error).
    pub fn study_if_any(&self) -> Result<Option<StudyRecord>> {
        read_optional(&self.study_json())
    }
}

/// `seed-S`.
pub fn seed_folder(seed: u64) -> String {
    format!("{SEED_PREFIX}{seed}")
}

/// The seed of a folder named `seed-S`.
pub fn parse_seed_folder(name: &str) -> Option<u64> {
    name.strip_prefix(SEED_PREFIX)?.parse().ok()
}

/// Reads and parses the JSON record at `path`.
pub fn read_record<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| Error::Record {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// [`read_record`], `None` when the file does not exist.
pub fn read_optional<T: DeserializeOwned>(path: &Path) -> Result<Option<T>> {
    match std::fs::metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        _ => read_record(path).map(Some),
    }
}

/// Writes `record` as pretty JSON at `path`, atomically.
pub fn write_record<T: Serialize>(path: &Path, record: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(record).map_err(|e| Error::Record {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    write_bytes_atomic(path, text.as_bytes())
}

/// `f64` fields that may be NaN: JSON has no NaN, so NaN is written as `null` and `null` reads
/// as NaN.
pub mod nan_as_null {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() {
            s.serialize_f64(*v)
        } else {
            s.serialize_none()
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
    }
}

/// The best validation value of a training call.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BestRecord {
    /// The metric's name (`rmse`, `miou`, ...).
    pub metric: String,
    pub value: f64,
    pub step: u64,
}

/// Where the wall time of a run went, in seconds. Training-call parts add up to about
/// `Summary::seconds`; `evaluation` is the evaluations after it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Timing {
    /// Building the network: for calibrated kernels the sampling plans and offsets of every
    /// layer (cached per process, so a second run of the same geometry pays little).
    pub build: f64,
    /// Opening the training and validation sources.
    pub data: f64,
    /// Training steps (batches, forward, backward, update; validation and checkpoints
    /// excluded).
    pub steps: f64,
    /// Validation passes during training.
    pub validation: f64,
    /// Writing checkpoints.
    pub checkpoints: f64,
    /// The evaluations after training (all of `eval/`), when they ran in this process.
    pub evaluation: Option<f64>,
}

impl Timing {
    /// One line: `build 0.4 s, data 0.1 s, steps 20.3 s, validation 3.1 s, ...`.
    pub fn describe(&self) -> String {
        let mut parts = vec![
            format!("build {:.1} s", self.build),
            format!("data {:.1} s", self.data),
            format!("steps {:.1} s", self.steps),
            format!("validation {:.1} s", self.validation),
            format!("checkpoints {:.1} s", self.checkpoints),
        ];
        if let Some(e) = self.evaluation {
            parts.push(format!("evaluation {e:.1} s"));
        }
        parts.join(", ")
    }
}

/// `summary.json`: what the last training call of a run did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub experiment: String,
    /// The seed of the network initialisation and the data order.
    #[serde(default)]
    pub seed: Option<u64>,
    /// Steps in total (including those before a resume) and in this call.
    pub steps: u64,
    pub steps_this_run: u64,
    /// Mean training loss of the first and last logging windows (NaN: none logged).
    #[serde(with = "nan_as_null")]
    pub first_loss: f64,
    #[serde(with = "nan_as_null")]
    pub last_loss: f64,
    pub best: Option<BestRecord>,
    /// Training throughput (images per second of step time).
    #[serde(with = "nan_as_null")]
    pub images_per_s: f64,
    /// Wall time of the training call.
    pub seconds: f64,
    /// Where that time went (absent in summaries of older versions).
    #[serde(default)]
    pub timing: Timing,
    pub last_checkpoint: PathBuf,
    pub best_checkpoint: Option<PathBuf>,
}

/// The details of one invocation in `run.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum InvocationDetails {
    /// `train`: resumed (from which step) or started (from which initial weights).
    Train {
        resume: bool,
        resume_step: Option<u64>,
        init: Option<PathBuf>,
    },
    /// `eval`: the checkpoint and the evaluations run.
    Eval {
        checkpoint: PathBuf,
        evaluations: Vec<String>,
    },
}

/// One invocation (`train` or `eval`) on a run directory.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Invocation {
    /// `train` or `eval`.
    pub command: String,
    pub unix_time: u64,
    /// `git describe --always --dirty` where it ran, if git answered.
    pub git: Option<String>,
    pub calibconv_version: String,
    /// As written in the experiment, and what it resolved to.
    pub device: String,
    pub resolved_device: Option<String>,
    pub torch_threads: i64,
    /// The process's command line.
    pub args: Vec<String>,
    /// The process id (absent in records of older versions).
    #[serde(default)]
    pub pid: Option<u32>,
    pub details: InvocationDetails,
}

/// How a [`Segment`] ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SegmentEnd {
    /// Trained to the end and evaluated.
    Complete,
    /// Stopped on a signal after writing its checkpoint (SLURM's warning before a time limit,
    /// preemption, Ctrl-C): running it again resumes.
    Interrupted,
    /// Stopped by an error.
    Failed,
}

/// One process's stretch of training on a run: a run that SLURM requeued twice has three.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Segment {
    /// When it started and ended (Unix seconds). `end` is absent while it runs, and stays
    /// absent when the process was killed before it could record it (`kill -9`, a lost node).
    pub start: f64,
    pub end: Option<f64>,
    /// The machine and the process.
    pub host: String,
    pub pid: u32,
    /// The SLURM job (`JOB_TASK` for an array task) and SLURM's restart count (requeues).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slurm_job: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slurm_restarts: Option<u32>,
    /// The step it started from and, when it ended, the step of the run's last checkpoint.
    pub first_step: u64,
    pub last_step: Option<u64>,
    /// How it ended (absent while it runs).
    pub reason: Option<SegmentEnd>,
    /// Interrupted: the signal and where; failed: the error (first line).
    pub message: Option<String>,
}

impl Segment {
    /// A segment of this process starting now at `first_step`, with the host name and the SLURM
    /// job of the environment (`SLURM_ARRAY_JOB_ID`/`SLURM_ARRAY_TASK_ID`, else `SLURM_JOB_ID`;
    /// `SLURM_RESTART_COUNT`).
    pub fn begin(first_step: u64) -> Segment {
        let env = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
        let slurm_job = match (env("SLURM_ARRAY_JOB_ID"), env("SLURM_ARRAY_TASK_ID")) {
            (Some(j), Some(t)) => Some(format!("{j}_{t}")),
            _ => env("SLURM_JOB_ID"),
        };
        Segment {
            start: unix_now(),
            end: None,
            host: host_name(),
            pid: std::process::id(),
            slurm_job,
            slurm_restarts: env("SLURM_RESTART_COUNT").and_then(|c| c.parse().ok()),
            first_step,
            last_step: None,
            reason: None,
            message: None,
        }
    }
}

/// This machine's host name (`?` if the OS does not say).
pub fn host_name() -> String {
    let mut buf = [0u8; 256];
    // SAFETY: gethostname writes at most `buf.len()` bytes into the buffer it is given.
    let rc = unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) };
    let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    if rc == 0 && end > 0 {
        String::from_utf8_lossy(&buf[..end]).into_owned()
    } else {
        "?".into()
    }
}

/// `run.json`: every invocation on a run directory, oldest first, and the segments of its
/// training (one per process that trained it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunRecord {
    pub experiment: String,
    pub invocations: Vec<Invocation>,
    /// Oldest first (absent in records of older versions).
    #[serde(default)]
    pub segments: Vec<Segment>,
}

impl RunRecord {
    /// The git revision of the latest invocation that recorded one.
    pub fn last_git(&self) -> Option<&str> {
        self.invocations.iter().rev().find_map(|i| i.git.as_deref())
    }
}

/// How a run ended in a sweep.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SweepStatus {
    Done,
    Failed,
    Blocked,
    /// Stopped on a signal after writing its checkpoint; the next sweep resumes it.
    Interrupted,
}

/// What a sweep laid over every experiment file: the profile and the `--set` overrides. Both
/// [`SweepRecord`] and [`StudyRecord`] flatten it, so its keys stand at their top level.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Overlay {
    /// The profile's name (empty for none) and file.
    pub profile: String,
    pub profile_file: Option<PathBuf>,
    /// `--set KEY=VALUE` overrides, as given.
    pub overrides: Vec<String>,
}

impl Overlay {
    /// The profile's name, `None` for a sweep without one.
    pub fn profile_name(&self) -> Option<&str> {
        Some(self.profile.as_str()).filter(|p| !p.is_empty())
    }
}

/// `sweep.json`: the sweep invocation that last ran (or failed to run) a run directory.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SweepRecord {
    pub experiment: String,
    /// The experiment file.
    pub file: PathBuf,
    /// The profile and overrides it ran with.
    #[serde(flatten)]
    pub overlay: Overlay,
    /// The replicate's seed (`None`: a sweep without seeds; the experiment's own seed).
    #[serde(default)]
    pub seed: Option<u64>,
    /// Dependency level and the runs it starts from.
    pub level: usize,
    pub depends_on: Vec<String>,
    pub git: Option<String>,
    pub status: SweepStatus,
    /// `train`, `resume` or `evaluate` (done runs).
    pub action: Option<String>,
    /// Wall time of the action.
    pub seconds: Option<f64>,
    /// When the action ended (Unix seconds; absent in records written before it existed): with
    /// `seconds`, the interval the run occupied, from which a report computes the elapsed wall
    /// time of a study whose runs overlap.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub finished_unix: Option<f64>,
    /// The error, with its cause chain (failed or blocked runs).
    pub error: Option<String>,
    /// The merged experiment text the run used.
    pub experiment_text: String,
}

/// The current time in Unix seconds (0 on a clock before 1970), as records store it.
pub fn unix_now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// One run of a study.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StudyRun {
    pub name: String,
    pub seed: Option<u64>,
    /// Its run directory, relative to the results folder (`seed-0/NAME`).
    pub dir: PathBuf,
    pub level: usize,
    pub depends_on: Vec<String>,
}

/// `RESULTS/study.json`: the sweep that last planned a results folder: which profile, which
/// seeds, which runs where.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StudyRecord {
    /// The experiments folder.
    pub dir: PathBuf,
    /// The profile and overrides of every run.
    #[serde(flatten)]
    pub overlay: Overlay,
    /// The replicates' seeds; empty for a sweep without seeds.
    pub seeds: Vec<u64>,
    /// Whether one baseline (in the first seed's folder) serves the fine-tunings of every seed.
    pub share_baseline: bool,
    pub git: Option<String>,
    pub runs: Vec<StudyRun>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn summaries_round_trip_with_nan_as_null_and_old_ones_read() {
        let s = Summary {
            experiment: "x".into(),
            seed: Some(3),
            steps: 4,
            steps_this_run: 4,
            first_loss: f64::NAN,
            last_loss: 0.5,
            best: None,
            images_per_s: 2.0,
            seconds: 1.0,
            timing: Timing {
                evaluation: Some(0.5),
                ..Default::default()
            },
            last_checkpoint: "a".into(),
            best_checkpoint: None,
        };
        let text = serde_json::to_string(&s).unwrap();
        assert!(text.contains("\"first_loss\":null"), "{text}");
        let back: Summary = serde_json::from_str(&text).unwrap();
        assert!(back.first_loss.is_nan());
        assert_eq!(back.timing, s.timing);
        // A summary of the version before timing and seed were recorded.
        let old = r#"{"experiment":"x","steps":1,"steps_this_run":1,"first_loss":1.0,
            "last_loss":1.0,"best":{"metric":"rmse","value":0.5,"step":1},"images_per_s":3.0,
            "seconds":2.0,"last_checkpoint":"l","best_checkpoint":null}"#;
        let o: Summary = serde_json::from_str(old).unwrap();
        assert_eq!(o.best.unwrap().metric, "rmse");
        assert_eq!(o.timing, Timing::default());
    }

    #[test]
    fn the_overlay_keys_stand_in_the_records_where_they_always_stood() {
        let overlay = Overlay {
            profile: "quick".into(),
            profile_file: Some("p.toml".into()),
            overrides: vec!["train.steps=2".into()],
        };
        let study = StudyRecord {
            dir: "e".into(),
            overlay: overlay.clone(),
            seeds: vec![0],
            share_baseline: false,
            git: None,
            runs: vec![],
        };
        let text = serde_json::to_string(&study).unwrap();
        assert_eq!(
            text,
            r#"{"dir":"e","profile":"quick","profile_file":"p.toml","overrides":["train.steps=2"],"seeds":[0],"share_baseline":false,"git":null,"runs":[]}"#
        );
        assert_eq!(serde_json::from_str::<StudyRecord>(&text).unwrap(), study);
        let sweep = SweepRecord {
            experiment: "x".into(),
            file: "x.toml".into(),
            overlay,
            seed: None,
            level: 0,
            depends_on: vec![],
            git: None,
            status: SweepStatus::Done,
            action: None,
            seconds: None,
            finished_unix: None,
            error: None,
            experiment_text: String::new(),
        };
        let text = serde_json::to_string(&sweep).unwrap();
        assert!(
            text.starts_with(
                r#"{"experiment":"x","file":"x.toml","profile":"quick","profile_file":"p.toml","overrides":["train.steps=2"],"seed":null,"level":0,"#
            ),
            "{text}"
        );
        assert_eq!(serde_json::from_str::<SweepRecord>(&text).unwrap(), sweep);
        assert_eq!(sweep.overlay.profile_name(), Some("quick"));
        assert_eq!(Overlay::default().profile_name(), None);
    }

    #[test]
    fn unreadable_records_are_errors_naming_the_file() {
        let tmp = tempfile::tempdir().unwrap();
        let run = RunDir::new(tmp.path());
        assert!(run.summary_if_any().unwrap().is_none());
        std::fs::write(run.summary_json(), "{\"experiment\": 1}").unwrap();
        let e = run.summary_if_any().unwrap_err().to_string();
        assert!(e.contains("summary.json"), "{e}");
        assert!(run
            .read_sweep()
            .unwrap_err()
            .to_string()
            .contains("sweep.json"));
    }

    #[test]
    fn replicates_are_seed_folders_or_the_folder_itself() {
        let tmp = tempfile::tempdir().unwrap();
        let results = ResultsDir::new(tmp.path());
        std::fs::create_dir_all(tmp.path().join("a")).unwrap();
        assert_eq!(
            results.replicates().unwrap(),
            [Replicate {
                seed: None,
                dir: tmp.path().to_path_buf()
            }]
        );
        for s in [10, 2] {
            std::fs::create_dir_all(results.seed_dir(s)).unwrap();
        }
        let seeds: Vec<_> = results
            .replicates()
            .unwrap()
            .iter()
            .map(|r| r.seed)
            .collect();
        assert_eq!(seeds, [Some(2), Some(10)]);
        assert_eq!(
            results.run_dir(Some(2), "n").path(),
            tmp.path().join("seed-2/n")
        );
        assert_eq!(parse_seed_folder("seed-x"), None);
    }
}
