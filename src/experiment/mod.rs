//! Experiment files: one TOML file describes one run (training and the evaluations after it).
//!
//! Reading goes text -> [`RawExperiment`] (serde, `deny_unknown_fields`: a misspelt key or value
//! is an error that names it and suggests the nearest valid one) -> [`RawExperiment::resolve`] ->
//! [`Experiment`]: checked values with every default filled in, paths made absolute, the camera
//! loaded. [`run`] trains and evaluates an [`Experiment`] in its own run directory.
//!
//! Relative paths (camera files, data sets, checkpoints, `output`) are relative to the current
//! directory, which is the repository root for the files in `experiments/`.
//!
//! Where things live:
//!
//! - [`schema`]: the file as written: the `Raw*` tables, the enums spelt in it, and [`parse`]
//!   (errors name the key and suggest the nearest valid one, via [`suggest`]).
//! - [`resolve`](mod@resolve): [`RawExperiment::resolve`], every check and default, section by
//!   section.
//! - [`spec`]: the resolved [`Experiment`] and its parts ([`InputSpec`], [`TrainSpec`],
//!   [`EvalSpec`], [`InitSpec`]), and [`parse_device`].
//! - [`source`]: the hook that opens data sources ([`SourceOpener`], [`DefaultOpener`]).
//! - [`run`](mod@run): training and evaluating an [`Experiment`] ([`train`], [`evaluate`]), and
//!   [`layout`]: the run directory's paths, typed records and lock.
//! - [`profile`]: profiles and `--set` overrides (TOML overlays merged before parsing);
//!   [`sweep`]: a folder of experiments with seeds as replicates, in dependency order;
//!   [`slurm`]: the sweep as SLURM job arrays.
//!
//! The `[input]` camera, padding and size define the network input and the calibrated offsets.
//! A data set folder is served padded to that size and must have been rendered with the same
//! geometry (checked when it is opened): e.g. `calibconv synth`'s default 128-px-wide F195 set
//! is `camera = "data/cameras/f195.toml"`, `padding = [0, 120]` (1080x960 -> 1080x1080),
//! `size = [128, 128]`.
//!
//! ```toml
//! name = "f195-depth-ft-calibrated"   # the run directory is OUTPUT/NAME
//! task = "depth"                      # depth | segmentation
//! seed = 0                            # network initialisation and data order
//! output = "runs"                     # default "runs"
//! device = "auto"                     # auto (CUDA if available) | cpu | cuda | cuda:N
//! data_root = "data/synth"            # relative `dataset` paths are relative to this
//!                                     # (itself relative to the current directory; default ".")
//!
//! [model]
//! preset = "small"                    # classic | classic-bilinear | small | tiny
//! kernel = "calibrated"               # standard | calibrated | camconv | calibrated-learned
//!                                     # (camconv: CAM-Convs' camera maps at the skip
//!                                     # connections; calibrated-learned: calibrated offsets plus
//!                                     # a learned offset branch; see calibconv::nn)
//! # base = 16, depth = 4, up = "transposed" | "bilinear": override the preset
//! # classes = 13                      # segmentation only (default 13)
//! init = { experiment = "pers-depth-bl" }   # or { checkpoint = "path.safetensors" }
//!
//! [input]
//! camera = "data/cameras/f195.toml"
//! width = 128                         # scale every camera of the experiment (input and evals)
//!                                     # to this image width, half-pixel convention, as
//!                                     # `calibconv synth --width` does (default: as written)
//! padding = [8, 0]                    # [right, bottom] added to the camera image, camera px
//! size = [120, 136]                   # [H, W] network input (default camera size + padding)
//! convention = "half-pixel"           # or "paper"
//!
//! [data]
//! train = { dataset = "data/synth/f195", split = "train" }   # fraction = 0.25: a subset
//!                                     # drawn with the seed, nested across fractions
//! val = { dataset = "data/synth/f195", split = "val" }
//! test = { toy = 32, split = "test" }
//!
//! [train]
//! epochs = 20                         # or steps = N
//! batch_size = 8
//! eval_batch_size = 8                 # default batch_size
//! loss = "l1"                         # depth: l1 | berhu; segmentation: cross-entropy
//! val_every = 500                     # steps (default: once per epoch)
//! val_metric = "rmse"                 # picks best.safetensors (default rmse / miou)
//! log_every = 20
//! checkpoint_every = 1000             # also save `last` this often (default: at validations)
//! images = 4                          # validation pictures in TensorBoard
//! radial_bins = 16
//! augment = { hflip = false, jitter = 0.2 }   # data sets only; see calibconv::data::loader
//!
//! [optimizer]
//! kind = "adam"                       # adam | adamw
//! lr = 1e-4
//! weight_decay = 0.0
//! betas = [0.9, 0.999]
//! eps = 1e-8
//!
//! [schedule]
//! kind = "cosine"                     # constant | step | cosine
//! warmup = 0                          # linear warm-up steps
//! min_lr = 1e-6                       # cosine
//! # every = 1000, gamma = 0.1         # step
//!
//! [[eval]]                            # evaluations after training (default: data.test)
//! name = "f195-calibrated"
//! data = { dataset = "data/synth/f195", split = "test" }
//! kernel = "calibrated"               # default: the model's kernel
//! # camera / padding / size / convention: default the [input] ones
//! radial_bins = 16
//! images = 4                          # prediction PNGs
//! ```

pub mod layout;
pub mod lock;
pub mod profile;
pub mod resolve;
pub mod run;
pub mod schema;
pub mod slurm;
pub mod source;
pub mod spec;
pub mod status;
pub mod suggest;
pub mod sweep;

use std::path::Path;

use crate::error::{Error, Result};
pub use run::{evaluate, train, RunOptions};
pub use schema::{
    parse, KernelName, LossName, OptimizerName, RawAugment, RawData, RawEval, RawExperiment,
    RawInit, RawInput, RawModel, RawOptimizer, RawSchedule, RawSource, RawTrain, ScheduleName,
    Task,
};
pub use source::{open_source, DefaultOpener, SourceOpener, SourceRequest, SourceSpec};
pub use spec::{parse_device, EvalSpec, Experiment, InitSpec, InputSpec, TrainSpec};

/// The output folder of an experiment without `output`.
pub const DEFAULT_OUTPUT: &str = "runs";

/// Reads and resolves the experiment file at `path`.
pub fn load(path: &Path) -> Result<Experiment> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse(&text, path)?.resolve(path, &text)
}

#[cfg(test)]
mod tests;
