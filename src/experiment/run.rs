//! Running an [`Experiment`]: its run directory, training, and the evaluations after it.
//!
//! The run directory's layout and records are [`super::layout`]'s. While a process trains or
//! evaluates a run it holds the run's lock ([`RunLock`]): a second `calibconv train` or
//! `calibconv eval` of the same run directory fails at once, naming the holder's PID.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde_json::json;
use tch::nn::VarStore;
use tch::Device;

use super::layout::{
    self, write_record, BestRecord, Invocation, InvocationDetails, RunDir, RunLock, RunRecord,
    Segment, SegmentEnd, Summary, Timing,
};

use super::{EvalSpec, Experiment, InitSpec, InputSpec, KernelName, SourceOpener, SourceRequest};
use crate::data::loader::Augment;
use crate::data::BatchSource;
use crate::error::{Error, Result};
use crate::eval::metrics::{Metric, RadialBins, ALL_METRICS};
use crate::eval::record::MetricsRecord;
use crate::eval::{self, principal_point, EvalOptions, Evaluation};
use crate::io::write_bytes_atomic;
use crate::nn::UNet;
use crate::plots;
use crate::train::checkpoint::{self, CheckpointInfo, TensorFile, FORMAT, FORMAT_VERSION};
use crate::train::csv::CsvLog;
use crate::train::stop::{self, StopFlag};
use crate::train::tensorboard::TensorBoard;
use crate::train::{self, Reporter, TrainConfig, TrainRun, TrainSummary};
use crate::util::fmt_f64;

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

/// A finished training call and the evaluations after it.
#[derive(Debug)]
pub struct TrainOutcome {
    pub summary: TrainSummary,
    pub evaluations: Vec<EvalOutcome>,
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

/// Opens the training source of `exp` as training does: shuffled by the experiment's seed
/// (the data order and the augmentations depend on the seed and the data set only, never on
/// the kernel), with the experiment's augmentations.
pub fn open_training_source(
    exp: &Experiment,
    opener: &dyn SourceOpener,
) -> Result<Box<dyn BatchSource>> {
    let t = &exp.train;
    opener.open(&source_for(
        &exp.train_data,
        &exp.input,
        t.batch_size,
        Some(exp.seed),
        t.augment,
    ))
}

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

fn radial_bins(input: &InputSpec, n: usize, r_max: Option<f64>) -> Result<RadialBins> {
    let centre = principal_point(&input.camera, &input.frame(), input.size).unwrap_or([
        (input.size[1] - 1) as f64 / 2.0,
        (input.size[0] - 1) as f64 / 2.0,
    ]);
    RadialBins::new(centre, input.size, n, r_max)
}

/// Resolves the initial checkpoint of `exp` (an error if it names a missing file).
pub fn init_checkpoint(exp: &Experiment) -> Result<Option<PathBuf>> {
    match &exp.init {
        None => Ok(None),
        Some(InitSpec::Checkpoint(p)) => {
            if p.is_file() {
                Ok(Some(p.clone()))
            } else {
                Err(Error::Config {
                    path: exp.file.clone(),
                    field: "model.init.checkpoint".into(),
                    message: format!("{}: no such file", p.display()),
                })
            }
        }
        Some(InitSpec::Experiment { name, checkpoints }) => best_or_last(checkpoints)
            .map(Some)
            .ok_or_else(|| Error::Config {
                path: exp.file.clone(),
                field: "model.init.experiment".into(),
                message: format!(
                    "experiment `{name}` has no checkpoint in {} yet: train it first",
                    checkpoints.display()
                ),
            }),
    }
}

/// Checks that `opts.resume` matches the state of `dir` (a checkpoint to resume, or none to
/// overwrite) and creates its checkpoint folder; warns when a resumed run's file changed.
fn prepare_run_dir(exp: &Experiment, opts: &RunOptions<'_>, dir: &RunDir) -> Result<()> {
    let ckdir = dir.checkpoints();
    let last = dir.last_checkpoint();
    if opts.resume && !last.is_file() {
        return Err(Error::Checkpoint {
            path: last,
            message: "nothing to resume: no checkpoint yet".into(),
        });
    }
    if !opts.resume && last.exists() {
        return Err(Error::Checkpoint {
            path: last,
            message: format!(
                "run `{}` already has checkpoints: resume it (--resume), or rename the \
                 experiment / remove {}",
                exp.name,
                exp.run_dir.display()
            ),
        });
    }
    std::fs::create_dir_all(&ckdir).map_err(|e| Error::io(&ckdir, e))?;
    if opts.resume && opts.verbose {
        if let Ok(old) = std::fs::read_to_string(dir.experiment_toml()) {
            if old != exp.text {
                eprintln!(
                    "warning: {} changed since the run started; resuming with the new file",
                    exp.file.display()
                );
            }
        }
    }
    Ok(())
}

/// Loads the starting weights of `exp` into `vs` (none when resuming: the trainer loads
/// `last`; else the initial checkpoint, if any) and records the invocation; returns the step
/// a resumed run continues from.
fn start_weights(
    exp: &Experiment,
    opts: &RunOptions<'_>,
    vs: &VarStore,
    last: &Path,
) -> Result<Option<u64>> {
    let mut init_from = None;
    let mut resume_step = None;
    if opts.resume {
        let info = TensorFile::open(last)?.info()?;
        resume_step = info.map(|i| i.step);
    } else if let Some(path) = init_checkpoint(exp)? {
        checkpoint::load_init(&path, vs, &exp.model)?;
        init_from = Some(path);
    }
    record_invocation(
        exp,
        "train",
        InvocationDetails::Train {
            resume: opts.resume,
            resume_step,
            init: init_from,
        },
        Some(resume_step.unwrap_or(0)),
    )?;
    Ok(resume_step)
}

/// Opens the validation source of `exp`, if it has one, in order and without augmentations.
fn open_validation_source(
    exp: &Experiment,
    opener: &dyn SourceOpener,
) -> Result<Option<Box<dyn BatchSource>>> {
    exp.val_data
        .as_ref()
        .map(|spec| {
            opener.open(&source_for(
                spec,
                &exp.input,
                exp.train.eval_batch_size,
                None,
                Augment::default(),
            ))
        })
        .transpose()
}

/// Trains `exp` (from scratch, from its initial checkpoint, or resumed), then runs its
/// evaluations on the best checkpoint, holding the run directory's lock.
pub fn train(exp: &Experiment, opts: &RunOptions<'_>) -> Result<TrainOutcome> {
    // An unavailable device is refused before the run directory is made.
    exp.device()?;
    let lock = run_dir(exp).lock()?;
    train_locked(exp, opts, &lock)
}

/// [`train()`] with the run's lock already held (by a sweep).
pub fn train_locked(
    exp: &Experiment,
    opts: &RunOptions<'_>,
    lock: &RunLock,
) -> Result<TrainOutcome> {
    check_lock(exp, lock)?;
    let dir = run_dir(exp);
    let device = exp.device()?;
    let last = dir.last_checkpoint();
    prepare_run_dir(exp, opts, &dir)?;
    let stored = dir.experiment_toml();
    // The files that describe the run: written now for a new run; for a resumed one only once
    // it has resumed (a refused resume leaves the run's description alone).
    let describe_run = || -> Result<()> {
        write_bytes_atomic(&stored, exp.text.as_bytes())?;
        write_record(&dir.config_json(), exp)
    };
    if !opts.resume {
        describe_run()?;
    }

    let t_build = Instant::now();
    let vs = VarStore::new(device);
    let model = build_model(exp, &vs, exp.kernel, &exp.input)?;
    let build_seconds = t_build.elapsed().as_secs_f64();
    let resume_step = start_weights(exp, opts, &vs, &last)?;
    let started = Started {
        vs: &vs,
        model: &model,
        resume_step,
        build_seconds,
        describe_run: &describe_run,
    };
    let result = train_started(exp, opts, lock, started);
    // Best effort: when the disk is full this write fails too, and the error that matters is
    // the training's.
    let _ = end_segment(exp, &result);
    result
}

/// A training call past its start: the network built and its weights loaded.
struct Started<'a> {
    vs: &'a VarStore,
    model: &'a UNet,
    resume_step: Option<u64>,
    build_seconds: f64,
    describe_run: &'a dyn Fn() -> Result<()>,
}

/// Trains and evaluates a started run (see [`train_locked`]).
fn train_started(
    exp: &Experiment,
    opts: &RunOptions<'_>,
    lock: &RunLock,
    started: Started<'_>,
) -> Result<TrainOutcome> {
    let Started {
        vs,
        model,
        resume_step,
        build_seconds,
        describe_run,
    } = started;
    let dir = run_dir(exp);
    let device = exp.device()?;
    let ckdir = dir.checkpoints();
    let t = &exp.train;
    let t_data = Instant::now();
    let train_src = open_training_source(exp, opts.opener)?;
    let val_src = open_validation_source(exp, opts.opener)?;
    let data_seconds = t_data.elapsed().as_secs_f64();
    let val_opts = EvalOptions {
        bins: radial_bins(&exp.input, t.radial_bins, None)?,
        panels: t.images,
        depth_loss: t.depth_loss,
        device,
        progress: false,
    };
    let per_epoch = train_src.len().div_ceil(t.batch_size) as u64;
    let cfg = train_config(exp, per_epoch, device, opts);
    let mut reporters: Vec<Box<dyn Reporter>> = vec![
        Box::new(TensorBoard::create(&dir.tb())?),
        Box::new(CsvLog::create(&exp.run_dir, resume_step)?),
    ];
    if opts.verbose {
        announce_training(
            exp,
            train_src.len(),
            val_src.as_ref().map(|v| v.len()),
            device,
        );
    }
    let summary = train::train(
        TrainRun {
            model,
            vs,
            train: train_src.as_ref(),
            val: val_src.as_deref().map(|s| (s, val_opts)),
            checkpoint_dir: &ckdir,
            info: checkpoint_info(exp),
            reporter: &mut reporters,
            resume: opts.resume,
        },
        &cfg,
    )?;
    drop(reporters); // closes the event file
    if opts.resume {
        describe_run()?;
    }
    let mut record = summary_record(exp, &summary, build_seconds, data_seconds);
    // Written before the evaluations: with it the run counts as trained (a sweep then only
    // evaluates); rewritten with their time after them.
    write_record(&dir.summary_json(), &record)?;
    if opts.verbose {
        eprintln!(
            "trained {} steps in {:.1} s ({:.1} images/s); loss {:.4} -> {:.4}",
            summary.steps_this_run,
            summary.seconds,
            summary.images_per_s,
            summary.first_loss,
            summary.last_loss
        );
    }
    let t_eval = Instant::now();
    let evaluations = evaluate_locked(exp, None, &[], opts, lock)?;
    record.timing.evaluation = Some(t_eval.elapsed().as_secs_f64());
    write_record(&dir.summary_json(), &record)?;
    if opts.verbose {
        eprintln!("{}: {}", exp.name, record.timing.describe());
    }
    Ok(TrainOutcome {
        summary,
        evaluations,
    })
}

/// The trainer's settings for `exp`: validation every `val_every` steps, else once per epoch
/// of `per_epoch` steps.
fn train_config(
    exp: &Experiment,
    per_epoch: u64,
    device: Device,
    opts: &RunOptions<'_>,
) -> TrainConfig {
    TrainConfig {
        length: exp.train.length,
        batch_size: exp.train.batch_size,
        adam: exp.train.adam,
        schedule: exp.train.schedule,
        depth_loss: exp.train.depth_loss,
        val_every: Some(exp.train.val_every.unwrap_or(per_epoch)),
        val_metric: exp.train.val_metric,
        log_every: exp.train.log_every,
        checkpoint_every: exp.train.checkpoint_every,
        device,
        progress: opts.progress,
        verbose: opts.verbose,
        stop: opts.stop,
    }
}

/// The metadata every checkpoint of `exp` carries (the trainer fills in the progress).
fn checkpoint_info(exp: &Experiment) -> CheckpointInfo {
    CheckpointInfo {
        format: FORMAT.into(),
        version: FORMAT_VERSION,
        model: exp.model,
        input_size: exp.input.size,
        kernel: exp.kernel.as_str().into(),
        camera_file: Some(exp.input.camera_file.clone()),
        camera_toml: Some(exp.input.camera_toml.clone()),
        padding: exp.input.padding,
        experiment: Some(exp.name.clone()),
        step: 0,
        epoch: 0,
        batch_in_epoch: 0,
        metrics: Default::default(),
        git: git_revision(),
    }
}

/// The status line before training `exp` on `train_len` (and `val_len`) samples.
fn announce_training(exp: &Experiment, train_len: usize, val_len: Option<usize>, device: Device) {
    eprintln!(
        "training {} ({}, {} kernels, {}x{} input, {} train samples{}) on {} (device = \"{}\") in {}",
        exp.name,
        checkpoint::describe(&exp.model),
        exp.kernel.as_str(),
        exp.input.size[0],
        exp.input.size[1],
        train_len,
        val_len.map(|n| format!(", {n} val")).unwrap_or_default(),
        crate::device::describe(device),
        exp.device,
        exp.run_dir.display()
    );
}

/// The `summary.json` record of a training call, its evaluation time still unknown.
fn summary_record(
    exp: &Experiment,
    summary: &TrainSummary,
    build_seconds: f64,
    data_seconds: f64,
) -> Summary {
    Summary {
        experiment: exp.name.clone(),
        seed: Some(exp.seed),
        steps: summary.steps,
        steps_this_run: summary.steps_this_run,
        first_loss: summary.first_loss,
        last_loss: summary.last_loss,
        best: summary.best.map(|(m, value, step)| BestRecord {
            metric: m.name().into(),
            value,
            step,
        }),
        images_per_s: summary.images_per_s,
        seconds: summary.seconds,
        timing: Timing {
            build: build_seconds,
            data: data_seconds,
            steps: summary.step_seconds,
            validation: summary.validation_seconds,
            checkpoints: summary.checkpoint_seconds,
            evaluation: None,
        },
        last_checkpoint: summary.last_checkpoint.clone(),
        best_checkpoint: summary.best_checkpoint.clone(),
    }
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
