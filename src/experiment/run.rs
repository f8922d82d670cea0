//! Running an [`Experiment`]: its run directory, training, and the evaluations after it.
//!
//! The run directory's layout and records are [`super::layout`]'s. While a process trains or
//! evaluates a run it holds the run's lock ([`RunLock`]): a second `calibconv train` or
//! `calibconv eval` of the same run directory fails at once, naming the holder's PID.
//!
//! This module holds the run directory's records, the model and its sources, and the
//! evaluations; [`training`] trains (and then evaluates through [`evaluate_locked`]).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use serde_json::json;
use tch::nn::VarStore;
use tch::Device;

use super::layout::{
    self, write_record, Invocation, InvocationDetails, RunDir, RunLock, RunRecord, Segment,
    SegmentEnd,
};

use super::{EvalSpec, Experiment, InputSpec, KernelName, SourceOpener, SourceRequest};
use crate::data::loader::Augment;
use crate::error::{Error, Result};
use crate::eval::metrics::{Metric, RadialBins, ALL_METRICS};
use crate::eval::record::MetricsRecord;
use crate::eval::{self, principal_point, EvalOptions, Evaluation};
use crate::io::write_bytes_atomic;
use crate::nn::UNet;
use crate::plots;
use crate::train;
use crate::train::checkpoint::{self, TensorFile};
use crate::train::stop::{self, StopFlag};
use crate::util::fmt_f64;

pub mod training;

pub use training::{init_checkpoint, open_training_source, train, train_locked, TrainOutcome};

/// How to run.
#[derive(Clone, Copy)]
pub struct RunOptions<'a> {
    /// Continue the run in the run directory (training only).
    pub resume: bool,
    /// Progress bars on stderr.
    pub progress: bool,
    /// Status lines on stderr.
    pub verbose: bool,
    /// Opens the data sources ([`super::DefaultOpener`] on the command line).
    pub opener: &'a dyn SourceOpener,
    /// Read once per training step and before each evaluation: when set, the run writes its
    /// checkpoint and stops with [`Error::Interrupted`] ([`StopFlag::process`] on the command
    /// line, where signals set it).
    pub stop: StopFlag,
}

/// One finished evaluation.
#[derive(Debug)]
pub struct EvalOutcome {
    pub name: String,
    /// Where its files are.
    pub dir: PathBuf,
    /// The checkpoint evaluated.
    pub checkpoint: PathBuf,
    pub evaluation: Evaluation,
}

/// The run directory of `exp`.
pub fn run_dir(exp: &Experiment) -> RunDir {
    RunDir::new(&exp.run_dir)
}

/// The checkpoint folder of a run.
pub fn checkpoint_dir(exp: &Experiment) -> PathBuf {
    run_dir(exp).checkpoints()
}

/// `git describe --always --dirty` of the current directory, if git answers.
pub fn git_revision() -> Option<String> {
    let out = std::process::Command::new("git")
        .args(["describe", "--always", "--dirty", "--abbrev=12"])
        .output()
        .ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
        .filter(|s| !s.is_empty())
}

/// Builds the experiment's U-Net under `vs` for `kernel` on `input`, initialised from the
/// experiment's seed (see [`train::seeded`]).
pub fn build_model(
    exp: &Experiment,
    vs: &VarStore,
    kernel: KernelName,
    input: &InputSpec,
) -> Result<UNet> {
    train::seeded(exp.seed, || {
        UNet::new(&vs.root(), &exp.model, &input.conv_kind(kernel), input.size)
    })
}

/// The best checkpoint of a run directory's `checkpoints/`, else its last, if any.
pub fn best_or_last(dir: &Path) -> Option<PathBuf> {
    [train::best_path(dir), train::last_path(dir)]
        .into_iter()
        .find(|p| p.is_file())
}

/// Appends an invocation record to `run.json`, and for training a [`Segment`] starting at
/// `segment` (the step it starts from); an unreadable `run.json` is an error: it is never
/// replaced.
fn record_invocation(
    exp: &Experiment,
    command: &str,
    details: InvocationDetails,
    segment: Option<u64>,
) -> Result<()> {
    let dir = run_dir(exp);
    let mut doc = dir.run_if_any()?.unwrap_or_else(|| RunRecord {
        experiment: exp.name.clone(),
        invocations: Vec::new(),
        segments: Vec::new(),
    });
    doc.segments.extend(segment.map(Segment::begin));
    doc.invocations.push(Invocation {
        command: command.into(),
        unix_time: std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0),
        git: git_revision(),
        calibconv_version: env!("CARGO_PKG_VERSION").into(),
        device: exp.device.clone(),
        resolved_device: exp.device().ok().map(crate::device::describe),
        torch_threads: i64::from(tch::get_num_threads()),
        args: std::env::args().collect(),
        pid: Some(std::process::id()),
        details,
    });
    write_record(&dir.run_json(), &doc)
}

/// Ends this process's open [`Segment`] in `run.json` (if it has one) with how training and
/// evaluating ended, and the step of the run's last checkpoint.
fn end_segment<T>(exp: &Experiment, result: &Result<T>) -> Result<()> {
    let dir = run_dir(exp);
    let Some(mut doc) = dir.run_if_any()? else {
        return Ok(());
    };
    let pid = std::process::id();
    let Some(seg) = doc
        .segments
        .iter_mut()
        .rev()
        .find(|s| s.pid == pid && s.end.is_none())
    else {
        return Ok(());
    };
    seg.end = Some(layout::unix_now());
    seg.last_step = checkpoint::read_info(&dir.last_checkpoint())
        .ok()
        .flatten()
        .map(|i| i.step);
    (seg.reason, seg.message) = match result {
        Ok(_) => (Some(SegmentEnd::Complete), None),
        Err(e) if e.is_interrupted() => (Some(SegmentEnd::Interrupted), Some(e.to_string())),
        Err(e) => (
            Some(SegmentEnd::Failed),
            e.to_string().lines().next().map(String::from),
        ),
    };
    write_record(&dir.run_json(), &doc)
}

/// `Err` unless `lock` is the lock of `exp`'s run directory.
fn check_lock(exp: &Experiment, lock: &RunLock) -> Result<()> {
    let want = run_dir(exp).lock_file();
    if lock.path() != want {
        return Err(Error::InvalidArgument(format!(
            "{} is not the lock of run {} ({})",
            lock.path().display(),
            exp.name,
            want.display()
        )));
    }
    Ok(())
}

/// The request for `spec` served as `input` (see [`SourceRequest`]).
fn source_for<'a>(
    spec: &'a super::SourceSpec,
    input: &'a InputSpec,
    batch_size: usize,
    shuffle: Option<u64>,
    augment: Augment,
) -> SourceRequest<'a> {
    SourceRequest {
        spec,
        batch_size,
        shuffle,
        input_size: input.size,
        camera: &input.camera,
        frame: input.frame(),
        augment,
    }
}

/// The radial bins of `n` rings around the principal point of `input` (the image centre where
/// it has none), out to `r_max` (default: the farthest pixel).
fn radial_bins(input: &InputSpec, n: usize, r_max: Option<f64>) -> Result<RadialBins> {
    let centre = principal_point(&input.camera, &input.frame(), input.size).unwrap_or([
        (input.size[1] - 1) as f64 / 2.0,
        (input.size[0] - 1) as f64 / 2.0,
    ]);
    RadialBins::new(centre, input.size, n, r_max)
}

/// Runs the evaluations of `exp` named in `only` (all if empty) on `checkpoint` (default: the
/// run's best, else its last), writing `eval/NAME/` and `evaluations.csv`, holding the run
/// directory's lock.
pub fn evaluate(
    exp: &Experiment,
    checkpoint: Option<&Path>,
    only: &[String],
    opts: &RunOptions<'_>,
) -> Result<Vec<EvalOutcome>> {
    let lock = run_dir(exp).lock()?;
    evaluate_locked(exp, checkpoint, only, opts, &lock)
}

/// Records `seconds` as the evaluation time of the run's `summary.json` (after a sweep
/// evaluated a trained run); nothing without a summary.
pub fn record_evaluation_time(exp: &Experiment, seconds: f64) -> Result<()> {
    let dir = run_dir(exp);
    if let Some(mut s) = dir.summary_if_any()? {
        s.timing.evaluation = Some(seconds);
        write_record(&dir.summary_json(), &s)?;
    }
    Ok(())
}

/// [`evaluate`] with the run's lock already held.
pub fn evaluate_locked(
    exp: &Experiment,
    checkpoint: Option<&Path>,
    only: &[String],
    opts: &RunOptions<'_>,
    lock: &RunLock,
) -> Result<Vec<EvalOutcome>> {
    check_lock(exp, lock)?;
    let selected = select_evaluations(exp, only)?;
    if selected.is_empty() {
        return Ok(Vec::new());
    }
    let ckpt = match checkpoint {
        Some(p) => p.to_path_buf(),
        None => best_or_last(&checkpoint_dir(exp)).ok_or_else(|| Error::Checkpoint {
            path: checkpoint_dir(exp),
            message: "no checkpoint to evaluate: train the experiment first or pass one".into(),
        })?,
    };
    let device = exp.device()?;
    std::fs::create_dir_all(&exp.run_dir).map_err(|e| Error::io(&exp.run_dir, e))?;
    record_invocation(
        exp,
        "eval",
        InvocationDetails::Eval {
            checkpoint: ckpt.clone(),
            evaluations: selected.iter().map(|e| e.name.clone()).collect(),
        },
        None,
    )?;
    let step = TensorFile::open(&ckpt)?.info()?.map(|i| i.step);
    let mut out = Vec::new();
    for spec in selected {
        if let Some(signal) = opts.stop.requested() {
            return Err(Error::Interrupted {
                signal: stop::signal_name(signal),
                what: format!("before evaluation `{}` of {}", spec.name, exp.name),
            });
        }
        out.push(evaluate_one(exp, spec, &ckpt, step, device, opts)?);
    }
    write_evaluations_csv(&exp.run_dir)?;
    Ok(out)
}

/// The evaluations of `exp` named in `only` (all if empty); a name it does not have is an
/// error.
fn select_evaluations<'a>(exp: &'a Experiment, only: &[String]) -> Result<Vec<&'a EvalSpec>> {
    let names: Vec<&str> = exp.evals.iter().map(|e| e.name.as_str()).collect();
    for o in only {
        if !names.contains(&o.as_str()) {
            let hint = super::suggest::did_you_mean(o, &names);
            return Err(Error::Config {
                path: exp.file.clone(),
                field: "eval".into(),
                message: format!(
                    "no evaluation named `{o}` (it has: {}){hint}",
                    if names.is_empty() {
                        "none".to_string()
                    } else {
                        names.join(", ")
                    }
                ),
            });
        }
    }
    Ok(exp
        .evals
        .iter()
        .filter(|e| only.is_empty() || only.contains(&e.name))
        .collect())
}

/// Runs one evaluation of `exp` on the checkpoint `ckpt` (saved at `step`) and writes
/// `eval/NAME/`.
fn evaluate_one(
    exp: &Experiment,
    spec: &EvalSpec,
    ckpt: &Path,
    step: Option<u64>,
    device: Device,
    opts: &RunOptions<'_>,
) -> Result<EvalOutcome> {
    let vs = VarStore::new(device);
    let model = build_model(exp, &vs, spec.kernel, &spec.input)?;
    checkpoint::load(ckpt, &vs, &exp.model)?;
    let source = opts.opener.open(&source_for(
        &spec.data,
        &spec.input,
        spec.batch_size,
        None,
        Augment::default(),
    ))?;
    let eopts = EvalOptions {
        bins: radial_bins(&spec.input, spec.radial_bins, spec.radial_max)?,
        panels: spec.images,
        depth_loss: exp.train.depth_loss,
        device,
        progress: opts.progress,
    };
    let e = eval::evaluate(&model, source.as_ref(), &eopts)?;
    let dir = run_dir(exp).eval_dir(&spec.name);
    let about = json!({
        "experiment": exp.name,
        "evaluation": spec.name,
        "data": spec.data.describe(),
        "kernel": spec.kernel.as_str(),
        "camera_file": spec.input.camera_file,
        "input_size": spec.input.size,
        "padding": spec.input.padding,
        "principal_point": eopts.bins.centre,
        "radial_edges": eopts.bins.edges,
        "checkpoint": ckpt,
        "checkpoint_step": step,
        "git": git_revision(),
    });
    e.write(&dir, &about)?;
    write_radial_plots(&dir, &e, spec)?;
    if opts.verbose {
        let line: Vec<String> = e
            .metrics
            .iter()
            .map(|(m, v)| format!("{m} {v:.4}"))
            .collect();
        eprintln!(
            "eval {} ({}, {} kernels, {} images): {}",
            spec.name,
            spec.data.describe(),
            spec.kernel.as_str(),
            e.images,
            line.join(", ")
        );
    }
    Ok(EvalOutcome {
        name: spec.name.clone(),
        dir,
        checkpoint: ckpt.to_path_buf(),
        evaluation: e,
    })
}

/// The paper's radial figures for one evaluation: `radial_<metric>.png` (mean and one standard
/// deviation over images per bin, against the bin centre in input pixels) for RMSE and delta1
/// (depth) or mIoU and mAcc (segmentation), in the kernel's colour (standard red, calibrated
/// blue). Bins without pixels are left out; a metric with no finite bin is skipped.
fn write_radial_plots(dir: &Path, e: &Evaluation, spec: &EvalSpec) -> Result<()> {
    let metrics = match e.head {
        crate::nn::Head::Depth => [Metric::Rmse, Metric::Delta1],
        crate::nn::Head::Segmentation { .. } => [Metric::MIoU, Metric::MAcc],
    };
    let colour = match spec.kernel {
        KernelName::Standard => plots::STANDARD_RED,
        KernelName::Calibrated => plots::CALIBRATED_BLUE,
        KernelName::CamConv => plots::CAMCONV_ORANGE,
        KernelName::CalibratedLearned => plots::LEARNED_PURPLE,
    };
    for m in metrics {
        let (mut x, mut mean, mut std) = (Vec::new(), Vec::new(), Vec::new());
        for r in &e.radial {
            if let Some((_, _, mu, sd)) = r.values.iter().find(|v| v.0 == m) {
                if r.pixels > 0 && mu.is_finite() {
                    x.push((r.r_lo + r.r_hi) / 2.0);
                    mean.push(*mu);
                    std.push(*sd);
                }
            }
        }
        if x.is_empty() {
            continue;
        }
        let curve = plots::Curve {
            label: format!("{} kernels", spec.kernel.as_str()),
            colour,
            x,
            mean,
            std,
        };
        let plot = plots::PlotSpec {
            title: format!("{}: {m} by distance to the principal point", spec.name),
            x_label: "distance to the principal point (input px)".into(),
            y_label: m.name().into(),
            ..Default::default()
        };
        plots::line_band_plot(&dir.join(format!("radial_{m}.png")), &plot, &[curve])?;
    }
    Ok(())
}

/// Rebuilds `RUN/evaluations.csv` from every `RUN/eval/*/metrics.json`: one row per
/// evaluation (sorted by name), columns `evaluation, data, kernel, checkpoint_step, images`
/// then every metric any of them has.
pub fn write_evaluations_csv(run_dir: &Path) -> Result<()> {
    let rd = RunDir::new(run_dir);
    let mut records = Vec::new();
    for name in rd.evaluation_names()? {
        records.push(MetricsRecord::read(&rd.metrics_json(&name))?);
    }
    records.sort_by(|a, b| a.about.evaluation.cmp(&b.about.evaluation));
    let present: BTreeSet<Metric> = records
        .iter()
        .flat_map(|r| r.metrics.keys().copied())
        .collect();
    let metrics: Vec<Metric> = ALL_METRICS
        .iter()
        .copied()
        .filter(|m| present.contains(m))
        .collect();
    let names: Vec<&str> = metrics.iter().map(|m| m.name()).collect();
    let mut csv = format!(
        "evaluation,data,kernel,checkpoint_step,images,{}\n",
        names.join(",")
    );
    let text = |s: &Option<String>| s.as_deref().unwrap_or("").replace(',', ";");
    for r in &records {
        let step = match r.about.other.get("checkpoint_step") {
            Some(serde_json::Value::Number(n)) => n.to_string(),
            _ => String::new(),
        };
        let values: Vec<String> = metrics
            .iter()
            .map(|m| fmt_f64(r.metrics.get(m).copied().flatten().unwrap_or(f64::NAN)))
            .collect();
        csv += &format!(
            "{},{},{},{},{},{}\n",
            text(&r.about.evaluation),
            text(&r.about.data),
            text(&r.about.kernel),
            step,
            r.images,
            values.join(",")
        );
    }
    write_bytes_atomic(&rd.evaluations_csv(), csv.as_bytes())
}
