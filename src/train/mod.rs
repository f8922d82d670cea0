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
//! All are written atomically, so a crash never leaves a truncated checkpoint; the pair `last.*`
//! is written in full (two temporary files) before either is replaced, so a full disk or an
//! I/O error leaves the previous pair whole and the run stops with
//! [`Error::Write`](crate::error::Error::Write) naming the file.
//!
//! # Stopping on a signal
//!
//! The trainer reads [`TrainConfig::stop`] after every step: when a stop was requested (by
//! SIGUSR1, SIGTERM or SIGINT, see [`stop`]), it writes `last.*` and returns
//! [`Error::Interrupted`](crate::error::Error::Interrupted); resuming from there gives the
//! weights of an uninterrupted run. A non-finite
//! loss or gradient norm stops training *before* the update with
//! [`Error::NonFinite`](crate::error::Error::NonFinite), naming the step and the last good
//! checkpoint (which the failed step never touched).

pub mod adam;
pub mod checkpoint;
pub mod csv;
pub mod pytorch;
pub mod schedule;
pub mod stop;
pub mod tensorboard;
pub mod tensors;
mod trainer;

use std::path::{Path, PathBuf};

use image::RgbImage;
use tch::nn::VarStore;
use tch::{Device, Tensor};

use crate::data::{Batch, BatchSource};
use crate::error::Result;
use crate::eval::metrics::Metric;
use crate::eval::{EvalOptions, Evaluation};
use crate::loss::{depth_loss, segmentation_loss, DepthLoss};
use crate::nn::{Head, UNet};
use adam::AdamConfig;
use checkpoint::CheckpointInfo;
use schedule::Schedule;

/// Where training output goes: scalars and images by step. Implementations: [`tensorboard`]
/// (event files) and [`csv`] (per-split CSV logs); the trainer only sees this trait.
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
    /// Read once per step: when set, training writes `last.*` after the step and stops with
    /// [`Error::Interrupted`](crate::error::Error::Interrupted) (see [`stop`]).
    pub stop: stop::StopFlag,
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

/// Trains `run.model` as `cfg` says. See the module docs for files, resume and errors.
pub fn train(run: TrainRun<'_>, cfg: &TrainConfig) -> Result<TrainSummary> {
    trainer::Trainer::new(run, cfg)?.run()
}

/// The metrics of an evaluation as `(name, value)` pairs.
pub fn scalar_pairs(e: &Evaluation) -> Vec<(String, f64)> {
    e.metrics
        .iter()
        .map(|(m, v)| (m.name().to_string(), *v))
        .collect()
}
