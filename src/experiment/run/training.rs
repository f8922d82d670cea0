//! Training an [`Experiment`] in its run directory: the starting weights (initial checkpoint
//! or resume), the data sources, the trainer's settings, the `summary.json` record, and the
//! evaluations after it ([`super::evaluate_locked`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use tch::nn::VarStore;
use tch::Device;

use super::{
    best_or_last, build_model, check_lock, end_segment, evaluate_locked, git_revision, radial_bins,
    record_invocation, run_dir, source_for, EvalOutcome, RunOptions,
};
use crate::data::loader::Augment;
use crate::data::BatchSource;
use crate::error::{Error, Result};
use crate::eval::EvalOptions;
use crate::experiment::layout::{
    write_record, BestRecord, InvocationDetails, RunDir, RunLock, Summary, Timing,
};
use crate::experiment::{Experiment, InitSpec, SourceOpener};
use crate::io::write_bytes_atomic;
use crate::nn::UNet;
use crate::train::checkpoint::{self, CheckpointInfo, TensorFile};
use crate::train::csv::CsvLog;
use crate::train::tensorboard::TensorBoard;
use crate::train::{self, Reporter, TrainConfig, TrainRun, TrainSummary};

/// A finished training call and the evaluations after it.
#[derive(Debug)]
pub struct TrainOutcome {
    pub summary: TrainSummary,
    pub evaluations: Vec<EvalOutcome>,
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
        camera_file: Some(exp.input.camera_file.clone()),
        camera_toml: Some(exp.input.camera_toml.clone()),
        padding: exp.input.padding,
        experiment: Some(exp.name.clone()),
        git: git_revision(),
        ..CheckpointInfo::new(exp.model, exp.input.size, exp.kernel.as_str())
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
