//! Training: Adam over a [`BatchSource`], learning-rate schedules, periodic validation with
//! best-checkpoint selection, atomic checkpoints, exact resume, and a stop on NaN / Inf.
//!
//! # Steps, epochs and the data order
//!
//! A step is one optimiser update on one batch. An epoch is one pass over the training source
//! (`ceil(len / batch_size)` batches, the last one possibly smaller); its order comes from the
//! source (seeded per epoch), so a run is fully determined by the seed that built the network
//! and the source's seed. Checkpoints record the step and the position in the data order
//! (epoch, batches of it used); [`TrainRun::resume`] restores the weights, the Adam moments
//! and that position, and asks the source for the same epoch with the used batches skipped,
//! so an interrupted run continues exactly where it stopped (a test checks the weights are
//! identical to an uninterrupted run).
//!
//! # Files (in `TrainRun::checkpoint_dir`)
//!
//! - `last.safetensors` + `last.optim.safetensors`: the latest state (every validation, every
//!   `checkpoint_every` steps and at the end);
//! - `best.safetensors`: the weights with the best validation value of `val_metric`.
//!
//! All are written atomically, so a crash never leaves a truncated checkpoint. A non-finite
//! loss or gradient norm stops training *before* the update with
//! [`Error::NonFinite`], naming the step and the last good checkpoint
//! (which the failed step never touched).

pub mod adam;
pub mod checkpoint;
pub mod pytorch;
pub mod schedule;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use image::RgbImage;
use tch::nn::VarStore;
use tch::{Device, Tensor};

use crate::data::{Batch, BatchSource};
use crate::error::{Error, Result};
use crate::eval::loss::{depth_loss, segmentation_loss, DepthLoss};
use crate::eval::metrics::Metric;
use crate::eval::{evaluate, progress_bar, EvalOptions, Evaluation};
use crate::nn::{Head, UNet};
use adam::{Adam, AdamConfig};
use checkpoint::CheckpointInfo;
use schedule::Schedule;

/// Where training output goes: scalars and images by step. Implementations (TensorBoard, CSV)
/// live in [`crate::report`]; the trainer only sees this trait.
pub trait Reporter {
    /// Scalars of `split` (`train`, `val`) at `step`.
    fn scalars(&mut self, split: &str, step: u64, values: &[(String, f64)]) -> Result<()>;
    /// A picture under `tag` at `step`.
    fn image(&mut self, tag: &str, step: u64, image: &RgbImage) -> Result<()>;
    /// Makes everything written so far durable.
    fn flush(&mut self) -> Result<()>;
}

/// A reporter that drops everything.
#[derive(Debug, Default)]
pub struct NoReporter;

impl Reporter for NoReporter {
    fn scalars(&mut self, _: &str, _: u64, _: &[(String, f64)]) -> Result<()> {
        Ok(())
    }
    fn image(&mut self, _: &str, _: u64, _: &RgbImage) -> Result<()> {
        Ok(())
    }
    fn flush(&mut self) -> Result<()> {
        Ok(())
    }
}

/// Several reporters, each sent everything in order.
impl Reporter for Vec<Box<dyn Reporter>> {
    fn scalars(&mut self, split: &str, step: u64, values: &[(String, f64)]) -> Result<()> {
        self.iter_mut()
            .try_for_each(|r| r.scalars(split, step, values))
    }
    fn image(&mut self, tag: &str, step: u64, image: &RgbImage) -> Result<()> {
        self.iter_mut().try_for_each(|r| r.image(tag, step, image))
    }
    fn flush(&mut self) -> Result<()> {
        self.iter_mut().try_for_each(|r| r.flush())
    }
}

/// How long to train.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Length {
    Epochs(u64),
    Steps(u64),
}

/// Training settings.
#[derive(Clone, Debug)]
pub struct TrainConfig {
    pub length: Length,
    /// The batch size the training source was opened with (to count steps per epoch).
    pub batch_size: usize,
    pub adam: AdamConfig,
    pub schedule: Schedule,
    pub depth_loss: DepthLoss,
    /// Validate every this many steps (and always at the end) when there is a validation set.
    pub val_every: Option<u64>,
    /// The validation metric that picks `best.safetensors`.
    pub val_metric: Metric,
    /// Log training scalars (means since the last log) at multiples of this many steps, and at
    /// the end.
    pub log_every: u64,
    /// Also write `last` every this many steps (validations always write it).
    pub checkpoint_every: Option<u64>,
    pub device: Device,
    /// Show progress bars (stderr).
    pub progress: bool,
    /// Print a status line at every validation (stderr).
    pub verbose: bool,
}

/// One training run.
pub struct TrainRun<'a> {
    pub model: &'a UNet,
    pub vs: &'a VarStore,
    pub train: &'a dyn BatchSource,
    /// Validation source and options (radial bins, pictures for TensorBoard).
    pub val: Option<(&'a dyn BatchSource, EvalOptions)>,
    pub checkpoint_dir: &'a Path,
    /// Written into every checkpoint (step, position and metrics are filled in).
    pub info: CheckpointInfo,
    pub reporter: &'a mut dyn Reporter,
    /// Continue from `checkpoint_dir/last.*` instead of starting at step 0.
    pub resume: bool,
}

/// What a finished run did.
#[derive(Clone, Debug)]
pub struct TrainSummary {
    /// Steps done in total (including those before a resume) and in this call.
    pub steps: u64,
    pub steps_this_run: u64,
    /// Mean training loss over the first and the last logging window of this call.
    pub first_loss: f64,
    pub last_loss: f64,
    /// Best validation value of `val_metric` and its step.
    pub best: Option<(Metric, f64, u64)>,
    /// Every validation: step and metrics.
    pub validations: Vec<(u64, Vec<(Metric, f64)>)>,
    /// Training throughput (images per second of training time, validation and checkpoints
    /// excluded) and wall time of this call.
    pub images_per_s: f64,
    pub seconds: f64,
    /// Of `seconds`: training steps (batches, forward, backward, update), validation passes,
    /// checkpoint writes.
    pub step_seconds: f64,
    pub validation_seconds: f64,
    pub checkpoint_seconds: f64,
    pub last_checkpoint: PathBuf,
    pub best_checkpoint: Option<PathBuf>,
}

/// Runs `f` (typically: build a network) right after `tch::manual_seed(seed)`, holding a
/// process-wide lock, so that the random initialisation depends on `seed` only, even when
/// several threads build networks or draw random numbers through this function at once
/// (libtorch's default generator is global).
pub fn seeded<T>(seed: u64, f: impl FnOnce() -> T) -> T {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _guard = LOCK.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    tch::manual_seed(seed as i64);
    f()
}

/// File of the latest weights in `dir`.
pub fn last_path(dir: &Path) -> PathBuf {
    dir.join("last.safetensors")
}

/// File of the latest optimiser state in `dir`.
pub fn last_optim_path(dir: &Path) -> PathBuf {
    dir.join("last.optim.safetensors")
}

/// File of the best weights in `dir`.
pub fn best_path(dir: &Path) -> PathBuf {
    dir.join("best.safetensors")
}

/// The training loss of one batch (on `device`).
pub fn batch_loss(model: &UNet, batch: &Batch, device: Device, depth: DepthLoss) -> Result<Tensor> {
    let out = model.f_forward_t(&batch.image.to_device(device), true)?;
    match model.config().head {
        Head::Depth => depth_loss(
            &out,
            &batch.depth.to_device(device),
            &batch.mask.to_device(device),
            depth,
        ),
        Head::Segmentation { .. } => segmentation_loss(&out, &batch.labels.to_device(device)),
    }
}

struct Best {
    metric: Metric,
    value: f64,
    step: u64,
}

/// Trains `run.model` as `cfg` says. See the module docs for files, resume and errors.
pub fn train(run: TrainRun<'_>, cfg: &TrainConfig) -> Result<TrainSummary> {
    let start = Instant::now();
    let TrainRun {
        model,
        vs,
        train,
        val,
        checkpoint_dir,
        mut info,
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
    let last = last_path(checkpoint_dir);
    let last_optim = last_optim_path(checkpoint_dir);
    let best_file = best_path(checkpoint_dir);
    let mut adam = Adam::new(vs, cfg.adam);
    let (mut step, mut epoch, mut pos) = (0u64, 0u64, 0u64);
    let mut best: Option<Best> = None;
    if resume {
        let loaded = checkpoint::load(&last, vs, model.config())?;
        let li = loaded.info.ok_or_else(|| Error::Checkpoint {
            path: last.clone(),
            message: "no calibconv metadata: cannot resume from it".into(),
        })?;
        let meta = adam.load(&last_optim)?;
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
        if saved_batch.is_some_and(|b| b != cfg.batch_size) {
            return Err(Error::Checkpoint {
                path: last_optim.clone(),
                message: format!(
                    "the run was trained with batch size {}, not {}: resuming would change \
                     the data order",
                    saved_batch.unwrap_or(0),
                    cfg.batch_size
                ),
            });
        }
        (step, epoch, pos) = (li.step, li.epoch, li.batch_in_epoch);
        if let (Some(m), Some(v), Some(s)) = (
            meta.get("best_metric")
                .and_then(|m| m.parse::<Metric>().ok()),
            meta.get("best_value").and_then(|v| v.parse::<f64>().ok()),
            meta.get("best_step").and_then(|v| v.parse::<u64>().ok()),
        ) {
            // A changed `val_metric` starts a new competition.
            if m == cfg.val_metric {
                best = Some(Best {
                    metric: m,
                    value: v,
                    step: s,
                });
            }
        }
    } else if last.exists() {
        return Err(Error::Checkpoint {
            path: last.clone(),
            message: "already exists: resume the run, or start it in a fresh directory".into(),
        });
    }
    let start_step = step;
    let bar = progress_bar(total, "train", cfg.progress);
    bar.set_position(step);
    let say = |msg: String| {
        if cfg.verbose && bar.is_hidden() {
            eprintln!("{msg}");
        } else if cfg.verbose {
            bar.println(msg);
        }
    };

    let save_last = |info: &mut CheckpointInfo,
                     adam: &Adam,
                     best: &Option<Best>,
                     step: u64,
                     epoch: u64,
                     pos: u64|
     -> Result<()> {
        let (e, p) = if pos >= per_epoch {
            (epoch + 1, 0)
        } else {
            (epoch, pos)
        };
        info.step = step;
        info.epoch = e;
        info.batch_in_epoch = p;
        let mut meta = HashMap::new();
        meta.insert("step".to_string(), step.to_string());
        meta.insert("batch_size".to_string(), cfg.batch_size.to_string());
        if let Some(b) = best {
            meta.insert("best_metric".into(), b.metric.name().into());
            meta.insert("best_value".into(), format!("{:e}", b.value));
            meta.insert("best_step".into(), b.step.to_string());
        }
        // Optimiser first: if the weights' write fails, the pair stays consistent on resume
        // (resume checks both steps agree).
        adam.save(&last_optim, meta)?;
        checkpoint::save(&last, vs, info)
    };

    let mut window = (0.0f64, 0u64);
    let (mut first_loss, mut last_loss) = (f64::NAN, f64::NAN);
    let mut images = 0u64;
    let mut train_secs = 0.0f64;
    let (mut val_secs, mut ckpt_secs) = (0.0f64, 0.0f64);
    let mut window_images = 0u64;
    let mut window_start = Instant::now();
    let mut validations = Vec::new();

    'epochs: while step < total {
        let mut seen = pos;
        let mut t0 = Instant::now();
        for batch in train.batches(epoch, pos as usize) {
            let batch = batch?;
            let b = batch.image.size()[0] as u64;
            let lr = cfg.schedule.lr_at(step, total);
            let loss = batch_loss(model, &batch, cfg.device, cfg.depth_loss)?;
            let loss_value = loss.double_value(&[]);
            let fail = |what: &str, value: f64| Error::NonFinite {
                step: step + 1,
                what: what.to_string(),
                value,
                last_good: last.exists().then(|| last.clone()),
            };
            if !loss_value.is_finite() {
                reporter.flush()?;
                return Err(fail("training loss", loss_value));
            }
            adam.zero_grad();
            loss.backward();
            let grad_norm = adam.grad_norm();
            if !grad_norm.is_finite() {
                reporter.flush()?;
                return Err(fail("gradient norm", grad_norm));
            }
            adam.step(lr);
            step += 1;
            seen += 1;
            images += b;
            window_images += b;
            window.0 += loss_value;
            window.1 += 1;
            train_secs += t0.elapsed().as_secs_f64();

            if step % cfg.log_every == 0 || step == total {
                let mean = window.0 / window.1 as f64;
                if first_loss.is_nan() {
                    first_loss = mean;
                }
                last_loss = mean;
                let rate = window_images as f64 / window_start.elapsed().as_secs_f64();
                reporter.scalars(
                    "train",
                    step,
                    &[
                        ("loss".into(), mean),
                        ("lr".into(), lr),
                        ("grad_norm".into(), grad_norm),
                        (
                            "epoch".into(),
                            epoch as f64 + seen as f64 / per_epoch as f64,
                        ),
                        ("images_per_s".into(), rate),
                    ],
                )?;
                bar.set_message(format!("loss {mean:.4} lr {lr:.2e} {rate:.1} img/s"));
                window = (0.0, 0);
                window_images = 0;
                window_start = Instant::now();
            }
            bar.set_position(step);

            let validate_now = step == total || cfg.val_every.is_some_and(|n| step % n == 0);
            let checkpoint_now =
                validate_now || cfg.checkpoint_every.is_some_and(|n| step % n == 0);
            if let (true, Some((source, opts))) = (validate_now, &val) {
                let t_val = Instant::now();
                let mut best_secs = 0.0;
                let e = evaluate(model, *source, opts)?;
                let values = scalar_pairs(&e);
                reporter.scalars("val", step, &values)?;
                for (i, (_, img)) in e.panels.iter().enumerate() {
                    reporter.image(&format!("val/prediction/{i}"), step, img)?;
                }
                let v = e.metric(cfg.val_metric).ok_or_else(|| {
                    Error::InvalidArgument(format!(
                        "validation metric `{}` does not exist for {} networks",
                        cfg.val_metric,
                        model.config().head.task_name()
                    ))
                })?;
                info.metrics = crate::eval::metric_map(&e);
                let improved = best
                    .as_ref()
                    .is_none_or(|b| cfg.val_metric.is_better(v, b.value));
                if improved {
                    best = Some(Best {
                        metric: cfg.val_metric,
                        value: v,
                        step,
                    });
                    let mut bi = info.clone();
                    bi.step = step;
                    let t_ckpt = Instant::now();
                    checkpoint::save(&best_file, vs, &bi)?;
                    best_secs = t_ckpt.elapsed().as_secs_f64();
                }
                say(format!(
                    "step {step}/{total}: train loss {last_loss:.4}, val {} {v:.4}{}",
                    cfg.val_metric,
                    if improved { " (best)" } else { "" }
                ));
                validations.push((step, e.metrics.clone()));
                val_secs += t_val.elapsed().as_secs_f64() - best_secs;
                ckpt_secs += best_secs;
            }
            if checkpoint_now {
                let t_ckpt = Instant::now();
                info.metrics.insert("train_loss".into(), last_loss);
                save_last(&mut info, &adam, &best, step, epoch, seen)?;
                reporter.flush()?;
                ckpt_secs += t_ckpt.elapsed().as_secs_f64();
            }
            if step >= total {
                break 'epochs;
            }
            t0 = Instant::now();
        }
        if seen != per_epoch {
            return Err(Error::InvalidArgument(format!(
                "the training source gave {seen} batches in epoch {epoch}, expected {per_epoch} \
                 ({} samples, batch size {})",
                train.len(),
                cfg.batch_size
            )));
        }
        epoch += 1;
        pos = 0;
    }
    bar.finish_and_clear();
    reporter.flush()?;
    Ok(TrainSummary {
        steps: step,
        steps_this_run: step - start_step,
        first_loss,
        last_loss,
        best: best.as_ref().map(|b| (b.metric, b.value, b.step)),
        validations,
        images_per_s: if train_secs > 0.0 {
            images as f64 / train_secs
        } else {
            f64::NAN
        },
        seconds: start.elapsed().as_secs_f64(),
        step_seconds: train_secs,
        validation_seconds: val_secs,
        checkpoint_seconds: ckpt_secs,
        last_checkpoint: last,
        best_checkpoint: best_file.exists().then_some(best_file),
    })
}

/// The metrics of an evaluation as `(name, value)` pairs.
pub fn scalar_pairs(e: &Evaluation) -> Vec<(String, f64)> {
    e.metrics
        .iter()
        .map(|(m, v)| (m.name().to_string(), *v))
        .collect()
}
