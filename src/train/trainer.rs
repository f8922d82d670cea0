//! The trainer behind [`super::train`]: one struct holding the run's state, with a method per
//! phase (resume, one optimiser step, logging, validation, checkpoint), so the loop over
//! epochs reads as the module docs describe it.

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Instant;

use indicatif::ProgressBar;
use tch::nn::VarStore;

use super::adam::Adam;
use super::checkpoint::{self, CheckpointInfo};
use super::{
    batch_loss, best_path, last_optim_path, last_path, scalar_pairs, Length, Reporter, TrainConfig,
    TrainRun, TrainSummary,
};
use crate::data::{Batch, BatchSource};
use crate::error::{Error, Result};
use crate::eval::metrics::Metric;
use crate::eval::{evaluate, EvalOptions};
use crate::nn::UNet;
use crate::util::progress_bar;

/// The best validation value so far and its step.
struct Best {
    metric: Metric,
    value: f64,
    step: u64,
}

/// Running sums of a call: the logging window, throughput and where the time went.
struct Stats {
    /// Loss sum and steps since the last log.
    window: (f64, u64),
    window_images: u64,
    window_start: Instant,
    first_loss: f64,
    last_loss: f64,
    images: u64,
    train_secs: f64,
    val_secs: f64,
    ckpt_secs: f64,
    validations: Vec<(u64, Vec<(Metric, f64)>)>,
}

/// One training run in progress.
pub(super) struct Trainer<'a, 'c> {
    model: &'a UNet,
    vs: &'a VarStore,
    train: &'a dyn BatchSource,
    val: Option<(&'a dyn BatchSource, EvalOptions)>,
    info: CheckpointInfo,
    reporter: &'a mut dyn Reporter,
    cfg: &'c TrainConfig,
    adam: Adam,
    per_epoch: u64,
    total: u64,
    last: PathBuf,
    last_optim: PathBuf,
    best_file: PathBuf,
    /// Steps done, the epoch, and batches of it used.
    step: u64,
    epoch: u64,
    pos: u64,
    start_step: u64,
    best: Option<Best>,
    bar: ProgressBar,
    stats: Stats,
    start: Instant,
}

impl<'a, 'c> Trainer<'a, 'c> {
    /// Checks the run, resumes it if asked (or refuses to overwrite an existing `last`).
    pub(super) fn new(run: TrainRun<'a>, cfg: &'c TrainConfig) -> Result<Self> {
        let start = Instant::now();
        let TrainRun {
            model,
            vs,
            train,
            val,
            checkpoint_dir,
            info,
            reporter,
            resume,
        } = run;
        if train.is_empty() || cfg.batch_size == 0 {
            return Err(Error::InvalidArgument(
                "training needs a non-empty source and a batch size > 0".into(),
            ));
        }
        if train.input_size() != model.input_size() {
            return Err(Error::InvalidArgument(format!(
                "the training source serves {:?} inputs, the network is built for {:?}",
                train.input_size(),
                model.input_size()
            )));
        }
        let per_epoch = train.len().div_ceil(cfg.batch_size) as u64;
        let total = match cfg.length {
            Length::Epochs(e) => e * per_epoch,
            Length::Steps(s) => s,
        };
        let mut t = Trainer {
            model,
            vs,
            train,
            val,
            info,
            reporter,
            cfg,
            adam: Adam::new(vs, cfg.adam),
            per_epoch,
            total,
            last: last_path(checkpoint_dir),
            last_optim: last_optim_path(checkpoint_dir),
            best_file: best_path(checkpoint_dir),
            step: 0,
            epoch: 0,
            pos: 0,
            start_step: 0,
            best: None,
            bar: ProgressBar::hidden(),
            stats: Stats {
                window: (0.0, 0),
                window_images: 0,
                window_start: start,
                first_loss: f64::NAN,
                last_loss: f64::NAN,
                images: 0,
                train_secs: 0.0,
                val_secs: 0.0,
                ckpt_secs: 0.0,
                validations: Vec::new(),
            },
            start,
        };
        if resume {
            t.resume()?;
        } else if t.last.exists() {
            return Err(Error::Checkpoint {
                path: t.last.clone(),
                message: "already exists: resume the run, or start it in a fresh directory".into(),
            });
        }
        t.start_step = t.step;
        t.bar = progress_bar(total, "train", cfg.progress);
        t.bar.set_position(t.step);
        t.stats.window_start = Instant::now();
        Ok(t)
    }

    /// Restores the weights, the Adam moments, the data position and the best value from
    /// `last.*`, after checking both files are from the same step and batch size.
    fn resume(&mut self) -> Result<()> {
        let (last, last_optim) = (&self.last, &self.last_optim);
        let loaded = checkpoint::load(last, self.vs, self.model.config())?;
        let li = loaded.info.ok_or_else(|| Error::Checkpoint {
            path: last.clone(),
            message: "no calibconv metadata: cannot resume from it".into(),
        })?;
        let meta = self.adam.load(last_optim)?;
        let optim_step = meta.get("step").and_then(|s| s.parse::<u64>().ok());
        if optim_step != Some(li.step) {
            return Err(Error::Checkpoint {
                path: last_optim.clone(),
                message: format!(
                    "optimiser state is from step {optim_step:?}, the weights from step {}",
                    li.step
                ),
            });
        }
        let saved_batch = meta.get("batch_size").and_then(|s| s.parse::<usize>().ok());
        if saved_batch.is_some_and(|b| b != self.cfg.batch_size) {
            return Err(Error::Checkpoint {
                path: last_optim.clone(),
                message: format!(
                    "the run was trained with batch size {}, not {}: resuming would change \
                     the data order",
                    saved_batch.unwrap_or(0),
                    self.cfg.batch_size
                ),
            });
        }
        (self.step, self.epoch, self.pos) = (li.step, li.epoch, li.batch_in_epoch);
        if let (Some(m), Some(v), Some(s)) = (
            meta.get("best_metric")
                .and_then(|m| m.parse::<Metric>().ok()),
            meta.get("best_value").and_then(|v| v.parse::<f64>().ok()),
            meta.get("best_step").and_then(|v| v.parse::<u64>().ok()),
        ) {
            // A changed `val_metric` starts a new competition.
            if m == self.cfg.val_metric {
                self.best = Some(Best {
                    metric: m,
                    value: v,
                    step: s,
                });
            }
        }
        Ok(())
    }

    /// Trains until `total` steps, then reports what it did.
    pub(super) fn run(mut self) -> Result<TrainSummary> {
        let train = self.train;
        'epochs: while self.step < self.total {
            let mut seen = self.pos;
            let mut t0 = Instant::now();
            for batch in train.batches(self.epoch, self.pos as usize) {
                let batch = batch?;
                let (lr, grad_norm) = self.optimise(&batch)?;
                seen += 1;
                self.stats.train_secs += t0.elapsed().as_secs_f64();
                let step = self.step;
                if step.is_multiple_of(self.cfg.log_every) || step == self.total {
                    self.log(lr, grad_norm, seen)?;
                }
                self.bar.set_position(step);
                let validate_now = step == self.total
                    || self.cfg.val_every.is_some_and(|n| step.is_multiple_of(n));
                if validate_now && self.val.is_some() {
                    self.validate()?;
                }
                let checkpointed = validate_now
                    || self
                        .cfg
                        .checkpoint_every
                        .is_some_and(|n| step.is_multiple_of(n));
                if checkpointed {
                    self.checkpoint(seen)?;
                }
                if step >= self.total {
                    break 'epochs;
                }
                if let Some(signal) = self.cfg.stop.requested() {
                    return Err(self.interrupted(signal, seen, checkpointed));
                }
                t0 = Instant::now();
            }
            if seen != self.per_epoch {
                return Err(Error::InvalidArgument(format!(
                    "the training source gave {seen} batches in epoch {}, expected {} \
                     ({} samples, batch size {})",
                    self.epoch,
                    self.per_epoch,
                    train.len(),
                    self.cfg.batch_size
                )));
            }
            self.epoch += 1;
            self.pos = 0;
        }
        self.bar.finish_and_clear();
        self.reporter.flush()?;
        Ok(self.summary())
    }

    /// One optimiser step on `batch`, stopped before the update on a non-finite loss or
    /// gradient norm. Returns the learning rate and the gradient norm.
    fn optimise(&mut self, batch: &Batch) -> Result<(f64, f64)> {
        let cfg = self.cfg;
        let b = batch.image.size()[0] as u64;
        let lr = cfg.schedule.lr_at(self.step, self.total);
        let loss = batch_loss(self.model, batch, cfg.device, cfg.depth_loss)?;
        let loss_value = loss.double_value(&[]);
        if !loss_value.is_finite() {
            self.reporter.flush()?;
            return Err(self.non_finite("training loss", loss_value));
        }
        self.adam.zero_grad();
        loss.backward();
        let grad_norm = self.adam.grad_norm();
        if !grad_norm.is_finite() {
            self.reporter.flush()?;
            return Err(self.non_finite("gradient norm", grad_norm));
        }
        self.adam.step(lr);
        self.step += 1;
        let s = &mut self.stats;
        s.images += b;
        s.window_images += b;
        s.window.0 += loss_value;
        s.window.1 += 1;
        Ok((lr, grad_norm))
    }

    /// The error of a non-finite `what` at the coming step.
    fn non_finite(&self, what: &str, value: f64) -> Error {
        Error::NonFinite {
            step: self.step + 1,
            what: what.to_string(),
            value,
            last_good: self.last.exists().then(|| self.last.clone()),
        }
    }

    /// Reports the training scalars of the window since the last log (`seen` batches of this
    /// epoch used) and starts a new window.
    fn log(&mut self, lr: f64, grad_norm: f64, seen: u64) -> Result<()> {
        let s = &mut self.stats;
        let mean = s.window.0 / s.window.1 as f64;
        if s.first_loss.is_nan() {
            s.first_loss = mean;
        }
        s.last_loss = mean;
        let rate = s.window_images as f64 / s.window_start.elapsed().as_secs_f64();
        let epoch = self.epoch as f64 + seen as f64 / self.per_epoch as f64;
        self.reporter.scalars(
            "train",
            self.step,
            &[
                ("loss".into(), mean),
                ("lr".into(), lr),
                ("grad_norm".into(), grad_norm),
                ("epoch".into(), epoch),
                ("images_per_s".into(), rate),
            ],
        )?;
        self.bar
            .set_message(format!("loss {mean:.4} lr {lr:.2e} {rate:.1} img/s"));
        s.window = (0.0, 0);
        s.window_images = 0;
        s.window_start = Instant::now();
        Ok(())
    }

    /// Evaluates on the validation source, reports it, and writes `best` if it improved.
    fn validate(&mut self) -> Result<()> {
        let Some((source, opts)) = &self.val else {
            return Ok(());
        };
        let (cfg, step) = (self.cfg, self.step);
        let t_val = Instant::now();
        let mut best_secs = 0.0;
        let e = evaluate(self.model, *source, opts)?;
        self.reporter.scalars("val", step, &scalar_pairs(&e))?;
        for (i, (_, img)) in e.panels.iter().enumerate() {
            self.reporter
                .image(&format!("val/prediction/{i}"), step, img)?;
        }
        let v = e.metric(cfg.val_metric).ok_or_else(|| {
            Error::InvalidArgument(format!(
                "validation metric `{}` does not exist for {} networks",
                cfg.val_metric,
                self.model.config().head.task_name()
            ))
        })?;
        self.info.metrics = crate::eval::metric_map(&e);
        let improved = self
            .best
            .as_ref()
            .is_none_or(|b| cfg.val_metric.is_better(v, b.value));
        if improved {
            self.best = Some(Best {
                metric: cfg.val_metric,
                value: v,
                step,
            });
            let mut bi = self.info.clone();
            bi.step = step;
            let t_ckpt = Instant::now();
            checkpoint::save(&self.best_file, self.vs, &bi)?;
            best_secs = t_ckpt.elapsed().as_secs_f64();
        }
        self.say(format!(
            "step {step}/{}: train loss {:.4}, val {} {v:.4}{}",
            self.total,
            self.stats.last_loss,
            cfg.val_metric,
            if improved { " (best)" } else { "" }
        ));
        self.stats.validations.push((step, e.metrics.clone()));
        self.stats.val_secs += t_val.elapsed().as_secs_f64() - best_secs;
        self.stats.ckpt_secs += best_secs;
        Ok(())
    }

    /// A status line on stderr (above the progress bar) when `verbose`.
    fn say(&self, msg: String) {
        if self.cfg.verbose && self.bar.is_hidden() {
            eprintln!("{msg}");
        } else if self.cfg.verbose {
            self.bar.println(msg);
        }
    }

    /// Stops after the current step on `signal`: writes `last.*` (unless this step already
    /// did), flushes the reporter and returns the [`Error::Interrupted`] to report; a failed
    /// write is returned instead.
    fn interrupted(&mut self, signal: i32, seen: u64, checkpointed: bool) -> Error {
        let saved = if checkpointed {
            self.reporter.flush()
        } else {
            self.checkpoint(seen)
        };
        if let Err(e) = saved {
            return e;
        }
        self.bar.finish_and_clear();
        Error::Interrupted {
            signal: super::stop::signal_name(signal),
            what: format!(
                "at step {} of {}; {} holds it",
                self.step,
                self.total,
                self.last.display()
            ),
        }
    }

    /// Writes `last.optim` and `last` (with the position after `seen` batches of this epoch)
    /// and flushes the reporter. Both files are written in full before either replaces its
    /// predecessor: a failed write (a full disk) leaves the previous pair whole.
    fn checkpoint(&mut self, seen: u64) -> Result<()> {
        let t_ckpt = Instant::now();
        self.info
            .metrics
            .insert("train_loss".into(), self.stats.last_loss);
        let (e, p) = if seen >= self.per_epoch {
            (self.epoch + 1, 0)
        } else {
            (self.epoch, seen)
        };
        self.info.step = self.step;
        self.info.epoch = e;
        self.info.batch_in_epoch = p;
        let mut meta = HashMap::new();
        meta.insert("step".to_string(), self.step.to_string());
        meta.insert("batch_size".to_string(), self.cfg.batch_size.to_string());
        if let Some(b) = &self.best {
            meta.insert("best_metric".into(), b.metric.name().into());
            meta.insert("best_value".into(), format!("{:e}", b.value));
            meta.insert("best_step".into(), b.step.to_string());
        }
        // Both written before either is renamed: the renames take no space, so the pair can
        // only disagree if the process dies between them (resume checks both steps agree).
        let optim = self.adam.stage(&self.last_optim, meta)?;
        let weights = checkpoint::stage(&self.last, self.vs, &self.info)?;
        optim.commit()?;
        weights.commit()?;
        self.reporter.flush()?;
        self.stats.ckpt_secs += t_ckpt.elapsed().as_secs_f64();
        Ok(())
    }

    fn summary(self) -> TrainSummary {
        let s = self.stats;
        TrainSummary {
            steps: self.step,
            steps_this_run: self.step - self.start_step,
            first_loss: s.first_loss,
            last_loss: s.last_loss,
            best: self.best.as_ref().map(|b| (b.metric, b.value, b.step)),
            validations: s.validations,
            images_per_s: if s.train_secs > 0.0 {
                s.images as f64 / s.train_secs
            } else {
                f64::NAN
            },
            seconds: self.start.elapsed().as_secs_f64(),
            step_seconds: s.train_secs,
            validation_seconds: s.val_secs,
            checkpoint_seconds: s.ckpt_secs,
            last_checkpoint: self.last,
            best_checkpoint: self.best_file.exists().then_some(self.best_file),
        }
    }
}
