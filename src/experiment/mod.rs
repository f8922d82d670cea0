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
//! kernel = "calibrated"               # standard | calibrated
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
//! train = { dataset = "data/synth/f195", split = "train" }
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
pub mod profile;
pub mod run;
pub mod slurm;
pub mod source;
pub mod suggest;
pub mod sweep;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use tch::Device;

use crate::camera::{self, Camera, CameraModel, PixelConvention};
use crate::data::loader::{Augment, ColorJitter};
use crate::data::NUM_CLASSES;
use crate::error::{Error, Result};
use crate::eval::metrics::{Metric, DEPTH_METRICS, SEGMENTATION_METRICS};
use crate::kernel::{kernel_focal, pyramid_sizes, InputFrame};
use crate::loss::DepthLoss;
use crate::nn::unet::PRESETS as PRESETS_LIST;
use crate::nn::{ConvKind, Head, UNetConfig, UpMode};
use crate::train::adam::AdamConfig;
use crate::train::schedule::{Decay, Schedule};
use crate::train::Length;
pub use run::{evaluate, train, RunOptions};
pub use source::{open_source, DefaultOpener, SourceOpener, SourceRequest, SourceSpec};

/// The output folder of an experiment without `output`.
pub const DEFAULT_OUTPUT: &str = "runs";

/// The task, as written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Task {
    Depth,
    Segmentation,
}

/// The conv kind, as written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum KernelName {
    Standard,
    Calibrated,
}

impl KernelName {
    /// `standard` or `calibrated`.
    pub fn as_str(&self) -> &'static str {
        match self {
            KernelName::Standard => "standard",
            KernelName::Calibrated => "calibrated",
        }
    }
}

/// The loss, as written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LossName {
    L1,
    Berhu,
    CrossEntropy,
}

/// The optimiser, as written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OptimizerName {
    Adam,
    Adamw,
}

/// The schedule, as written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ScheduleName {
    Constant,
    Step,
    Cosine,
}

/// An experiment file as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawExperiment {
    /// Names the run directory.
    pub name: String,
    pub task: Task,
    pub description: Option<String>,
    pub seed: Option<u64>,
    pub output: Option<PathBuf>,
    pub device: Option<String>,
    pub data_root: Option<PathBuf>,
    pub model: RawModel,
    pub input: RawInput,
    pub data: RawData,
    pub train: RawTrain,
    pub optimizer: RawOptimizer,
    pub schedule: Option<RawSchedule>,
    #[serde(default, rename = "eval")]
    pub evals: Vec<RawEval>,
}

/// `[model]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawModel {
    pub preset: String,
    pub kernel: KernelName,
    pub base: Option<i64>,
    pub depth: Option<usize>,
    pub up: Option<UpMode>,
    pub classes: Option<i64>,
    pub init: Option<RawInit>,
}

/// `model.init`: exactly one of the two.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawInit {
    pub experiment: Option<String>,
    pub checkpoint: Option<PathBuf>,
}

/// `[input]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawInput {
    pub camera: PathBuf,
    pub width: Option<usize>,
    pub padding: Option<[usize; 2]>,
    pub size: Option<[i64; 2]>,
    pub convention: Option<PixelConvention>,
}

/// `[data]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawData {
    pub train: RawSource,
    pub val: Option<RawSource>,
    pub test: Option<RawSource>,
}

/// A data source: exactly one of `dataset` and `toy`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawSource {
    pub dataset: Option<PathBuf>,
    pub toy: Option<usize>,
    pub split: String,
}

/// `[train]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawTrain {
    pub epochs: Option<u64>,
    pub steps: Option<u64>,
    pub batch_size: usize,
    pub eval_batch_size: Option<usize>,
    pub loss: Option<LossName>,
    pub val_every: Option<u64>,
    pub val_metric: Option<String>,
    pub log_every: Option<u64>,
    pub checkpoint_every: Option<u64>,
    pub images: Option<usize>,
    pub radial_bins: Option<usize>,
    pub augment: Option<RawAugment>,
}

/// `train.augment`: augmentations of the training data set (see [`crate::data::loader`]:
/// only those that keep the calibration valid).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawAugment {
    /// Horizontal flips (refused by the loader unless the principal point is centred).
    pub hflip: Option<bool>,
    /// Brightness, contrast and saturation jitter amplitude (e.g. 0.2), none if absent.
    pub jitter: Option<f32>,
}

/// `[optimizer]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawOptimizer {
    pub kind: Option<OptimizerName>,
    pub lr: f64,
    pub weight_decay: Option<f64>,
    pub betas: Option<[f64; 2]>,
    pub eps: Option<f64>,
}

/// `[schedule]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawSchedule {
    pub kind: ScheduleName,
    pub warmup: Option<u64>,
    pub every: Option<u64>,
    pub gamma: Option<f64>,
    pub min_lr: Option<f64>,
}

/// `[[eval]]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawEval {
    pub name: String,
    pub data: RawSource,
    pub kernel: Option<KernelName>,
    pub camera: Option<PathBuf>,
    pub padding: Option<[usize; 2]>,
    pub size: Option<[i64; 2]>,
    pub convention: Option<PixelConvention>,
    pub radial_bins: Option<usize>,
    pub radial_max: Option<f64>,
    pub images: Option<usize>,
    pub batch_size: Option<usize>,
}

/// A camera, the frame that makes the network input from its image, and the input size.
#[derive(Clone, Debug, Serialize)]
pub struct InputSpec {
    /// Absolute path of the camera file, and its text (recorded in checkpoints).
    pub camera_file: PathBuf,
    pub camera_toml: String,
    #[serde(skip)]
    pub camera: Arc<Camera>,
    /// `[p_w, p_h]` camera pixels.
    pub padding: [usize; 2],
    pub convention: PixelConvention,
    /// Network input `[H, W]`.
    pub size: [i64; 2],
}

impl InputSpec {
    /// The frame the calibrated offsets use.
    pub fn frame(&self) -> InputFrame {
        InputFrame {
            padding: self.padding,
            convention: self.convention,
        }
    }

    /// The conv kind for `kernel` on this input.
    pub fn conv_kind(&self, kernel: KernelName) -> ConvKind {
        match kernel {
            KernelName::Standard => ConvKind::Standard,
            KernelName::Calibrated => ConvKind::Calibrated {
                camera: self.camera.clone(),
                frame: self.frame(),
            },
        }
    }
}

/// Where the initial weights come from.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum InitSpec {
    /// Another experiment's best checkpoint (its last if it has no best), in the same output
    /// folder: `OUTPUT/NAME/checkpoints/`.
    Experiment { name: String, checkpoints: PathBuf },
    /// A checkpoint file (calibconv or a PyTorch state dict in safetensors).
    Checkpoint(PathBuf),
}

/// One evaluation after training.
#[derive(Clone, Debug, Serialize)]
pub struct EvalSpec {
    pub name: String,
    pub data: SourceSpec,
    pub kernel: KernelName,
    pub input: InputSpec,
    pub radial_bins: usize,
    pub radial_max: Option<f64>,
    pub images: usize,
    pub batch_size: usize,
}

/// Training settings, resolved.
#[derive(Clone, Debug, Serialize)]
pub struct TrainSpec {
    #[serde(serialize_with = "ser_length")]
    pub length: Length,
    pub batch_size: usize,
    pub eval_batch_size: usize,
    pub depth_loss: DepthLoss,
    /// `None`: once per epoch.
    pub val_every: Option<u64>,
    #[serde(serialize_with = "ser_metric")]
    pub val_metric: Metric,
    pub log_every: u64,
    pub checkpoint_every: Option<u64>,
    pub images: usize,
    pub radial_bins: usize,
    /// Training-set augmentations.
    #[serde(skip)]
    pub augment: Augment,
    pub adam: AdamConfig,
    pub schedule: Schedule,
}

fn ser_length<S: serde::Serializer>(l: &Length, s: S) -> std::result::Result<S::Ok, S::Error> {
    match l {
        Length::Epochs(e) => s.serialize_str(&format!("{e} epochs")),
        Length::Steps(n) => s.serialize_str(&format!("{n} steps")),
    }
}

fn ser_metric<S: serde::Serializer>(m: &Metric, s: S) -> std::result::Result<S::Ok, S::Error> {
    s.serialize_str(m.name())
}

/// A checked experiment.
#[derive(Clone, Debug, Serialize)]
pub struct Experiment {
    pub name: String,
    pub description: Option<String>,
    /// The file it was read from (absolute) and its text.
    pub file: PathBuf,
    #[serde(skip)]
    pub text: String,
    pub seed: u64,
    /// `OUTPUT/NAME`, absolute.
    pub run_dir: PathBuf,
    pub output: PathBuf,
    /// As written (`auto`, `cpu`, `cuda`, `cuda:N`).
    pub device: String,
    pub model: UNetConfig,
    pub kernel: KernelName,
    pub init: Option<InitSpec>,
    pub input: InputSpec,
    pub train_data: SourceSpec,
    pub val_data: Option<SourceSpec>,
    pub test_data: Option<SourceSpec>,
    pub train: TrainSpec,
    pub evals: Vec<EvalSpec>,
}

impl Experiment {
    /// The device named by `device`.
    pub fn device(&self) -> Result<Device> {
        parse_device(&self.device)
    }
}

/// `auto` | `cpu` | `cuda` | `cuda:N`.
pub fn parse_device(s: &str) -> Result<Device> {
    match s {
        "auto" => Ok(Device::cuda_if_available()),
        "cpu" => Ok(Device::Cpu),
        "cuda" => Ok(Device::Cuda(0)),
        other => other
            .strip_prefix("cuda:")
            .and_then(|n| n.parse::<usize>().ok())
            .map(Device::Cuda)
            .ok_or_else(|| {
                Error::InvalidArgument(format!(
                    "unknown device `{other}` (expected auto, cpu, cuda or cuda:N)"
                ))
            }),
    }
}

/// Reads and resolves the experiment file at `path`.
pub fn load(path: &Path) -> Result<Experiment> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse(&text, path)?.resolve(path, &text)
}

/// The dotted name of the table around byte `offset` of a TOML text (`optimizer`, `eval`, ...;
/// empty at the top level), from the last `[header]` before it.
fn table_at(text: &str, offset: usize) -> String {
    let mut table = String::new();
    for line in text[..offset.min(text.len())].lines() {
        let l = line.trim();
        if l.starts_with('[') {
            table = l.trim_matches(|c| c == '[' || c == ']').trim().to_string();
        }
    }
    table
}

/// Parses an experiment file's text (`path` only names it in errors).
pub fn parse(text: &str, path: &Path) -> Result<RawExperiment> {
    toml::from_str(text).map_err(|e| {
        let hint = suggest::hint(e.message());
        let mut message = e.to_string().trim_end().to_string();
        if let Some(h) = hint {
            message = format!("{message}\nhelp: {h}");
        }
        match (
            suggest::parse_unknown(e.message()),
            e.span().map(|s| s.start),
        ) {
            (Some((_, name, _)), Some(at)) => {
                let table = table_at(text, at);
                let field = if table.is_empty() {
                    name
                } else {
                    format!("{table}.{name}")
                };
                Error::Config {
                    path: path.to_path_buf(),
                    field,
                    message,
                }
            }
            _ => Error::Toml {
                path: path.to_path_buf(),
                message,
            },
        }
    })
}

/// `x > 0` (false for NaN).
fn positive(x: f64) -> bool {
    x > 0.0
}

fn absolute(p: &Path) -> Result<PathBuf> {
    std::path::absolute(p).map_err(|e| Error::io(p, e))
}

impl RawSource {
    fn resolve(self, cfg: &Path, field: &str, root: &Path) -> Result<SourceSpec> {
        let bad = |message: &str| Error::Config {
            path: cfg.to_path_buf(),
            field: field.to_string(),
            message: message.to_string(),
        };
        if self.split.is_empty() {
            return Err(bad("`split` must not be empty"));
        }
        match (self.dataset, self.toy) {
            (Some(p), None) => Ok(SourceSpec::Dataset {
                path: absolute(&root.join(p))?,
                split: self.split,
            }),
            (None, Some(0)) => Err(bad("`toy` needs at least one sample")),
            (None, Some(n)) => Ok(SourceSpec::Toy {
                samples: n,
                split: self.split,
            }),
            _ => Err(bad(
                "give exactly one of `dataset = \"FOLDER\"` and `toy = SAMPLES`",
            )),
        }
    }
}

/// Loads a camera and builds the input spec; `field` names the camera key in errors.
fn input_spec(
    cfg: &Path,
    field: &str,
    camera_path: &Path,
    width: Option<usize>,
    padding: Option<[usize; 2]>,
    size: Option<[i64; 2]>,
    convention: Option<PixelConvention>,
) -> Result<InputSpec> {
    let bad = |f: &str, message: String| Error::Config {
        path: cfg.to_path_buf(),
        field: f.to_string(),
        message,
    };
    let camera_file = absolute(camera_path)?;
    let camera_toml = std::fs::read_to_string(&camera_file)
        .map_err(|e| bad(field, format!("{}: {e}", camera_file.display())))?;
    let mut camera = camera::load(&camera_file).map_err(|e| bad(field, e.to_string()))?;
    let mut camera_toml = camera_toml;
    if let Some(w) = width {
        if w == 0 {
            return Err(bad("input.width", "must be positive".into()));
        }
        let s = w as f64 / camera.size()[0] as f64;
        camera = camera.rescaled([s, s], PixelConvention::HalfPixel);
        let note = format!(
            "{} rescaled to {}x{} (half-pixel convention) by input.width",
            camera_file.display(),
            camera.size()[0],
            camera.size()[1]
        );
        camera_toml = camera::to_toml(&camera, &[], None, Some(&note));
    }
    let padding = padding.unwrap_or([0, 0]);
    let [w, h] = camera.size();
    let size = size.unwrap_or([(h + padding[1]) as i64, (w + padding[0]) as i64]);
    if size.iter().any(|&s| s < 1) {
        return Err(bad(
            &field.replace("camera", "size"),
            format!("must be positive, got {size:?}"),
        ));
    }
    Ok(InputSpec {
        camera_file,
        camera_toml,
        camera: Arc::new(camera),
        padding,
        convention: convention.unwrap_or_default(),
        size,
    })
}

/// Checks that calibrated 3x3 kernels fit every level of `model` on `input` (the deepest level
/// is the narrowest), so a bad combination fails at resolve time rather than at build time.
fn check_calibrated(cfg: &Path, field: &str, model: &UNetConfig, input: &InputSpec) -> Result<()> {
    let sizes = pyramid_sizes(
        [input.size[0] as usize, input.size[1] as usize],
        model.depth,
    );
    let deepest = sizes[model.depth];
    if deepest[0] == 0 || deepest[1] == 0 {
        return Err(Error::Config {
            path: cfg.to_path_buf(),
            field: field.to_string(),
            message: format!(
                "a {}x{} input is too small for a U-Net of depth {}",
                input.size[0], input.size[1], model.depth
            ),
        });
    }
    kernel_focal(3, input.camera.fov(), deepest[1])
        .map(|_| ())
        .map_err(|e| Error::Config {
            path: cfg.to_path_buf(),
            field: field.to_string(),
            message: format!(
                "calibrated kernels at the deepest level ({}x{}): {e}",
                deepest[0], deepest[1]
            ),
        })
}

fn check_name(cfg: &Path, field: &str, name: &str) -> Result<()> {
    let ok = !name.is_empty()
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
        && !name.starts_with('.');
    if ok {
        Ok(())
    } else {
        Err(Error::Config {
            path: cfg.to_path_buf(),
            field: field.to_string(),
            message: format!("`{name}`: use letters, digits, `-`, `_` and `.` (it names a folder)"),
        })
    }
}

impl RawExperiment {
    /// Checks every value and fills in the defaults; `path` is the file (for relative-path
    /// errors and the record), `text` its content.
    pub fn resolve(self, path: &Path, text: &str) -> Result<Experiment> {
        let cfg = path;
        let bad = |field: &str, message: String| Error::Config {
            path: cfg.to_path_buf(),
            field: field.to_string(),
            message,
        };
        check_name(cfg, "name", &self.name)?;
        let device = self.device.unwrap_or_else(|| "auto".to_string());
        parse_device(&device).map_err(|e| bad("device", e.to_string()))?;

        // Model.
        let head = match self.task {
            Task::Depth => {
                if self.model.classes.is_some() {
                    return Err(bad(
                        "model.classes",
                        "only for task = \"segmentation\"".into(),
                    ));
                }
                Head::Depth
            }
            Task::Segmentation => {
                let classes = self.model.classes.unwrap_or(NUM_CLASSES as i64);
                if classes < 2 {
                    return Err(bad("model.classes", format!("need >= 2, got {classes}")));
                }
                Head::Segmentation { classes }
            }
        };
        let mut model = UNetConfig::preset(&self.model.preset, head).map_err(|_| {
            let hint = suggest::nearest(&self.model.preset, &PRESETS_LIST)
                .map(|b| format!("; did you mean `{b}`?"))
                .unwrap_or_default();
            bad(
                "model.preset",
                format!(
                    "unknown preset `{}` (expected one of {}){hint}",
                    self.model.preset,
                    PRESETS_LIST.join(", ")
                ),
            )
        })?;
        if let Some(b) = self.model.base {
            model.base = b;
        }
        if let Some(d) = self.model.depth {
            model.depth = d;
        }
        if let Some(u) = self.model.up {
            model.up = u;
        }
        model.check().map_err(|e| bad("model", e.to_string()))?;
        let kernel = self.model.kernel;

        let init = match self.model.init {
            None => None,
            Some(RawInit {
                experiment: Some(name),
                checkpoint: None,
            }) => {
                check_name(cfg, "model.init.experiment", &name)?;
                if name == self.name {
                    return Err(bad(
                        "model.init.experiment",
                        "an experiment cannot start from its own checkpoints (use --resume)".into(),
                    ));
                }
                Some((name, None))
            }
            Some(RawInit {
                experiment: None,
                checkpoint: Some(p),
            }) => Some((String::new(), Some(absolute(&p)?))),
            Some(_) => {
                return Err(bad(
                    "model.init",
                    "give exactly one of `experiment = \"NAME\"` and `checkpoint = \"FILE\"`"
                        .into(),
                ))
            }
        };

        // Input.
        let i = self.input;
        let width = i.width;
        let input = input_spec(
            cfg,
            "input.camera",
            &i.camera,
            width,
            i.padding,
            i.size,
            i.convention,
        )?;
        if kernel == KernelName::Calibrated {
            check_calibrated(cfg, "input.size", &model, &input)?;
        }

        // Data.
        let root = self.data_root.unwrap_or_else(|| PathBuf::from("."));
        let root = root.as_path();
        let train_data = self.data.train.resolve(cfg, "data.train", root)?;
        let val_data = self
            .data
            .val
            .map(|s| s.resolve(cfg, "data.val", root))
            .transpose()?;
        let raw_test = self.data.test.clone();
        let test_data = self
            .data
            .test
            .map(|s| s.resolve(cfg, "data.test", root))
            .transpose()?;

        // Training.
        let t = self.train;
        let length = match (t.epochs, t.steps) {
            (Some(e), None) if e > 0 => Length::Epochs(e),
            (None, Some(s)) if s > 0 => Length::Steps(s),
            _ => {
                return Err(bad(
                    "train",
                    "give exactly one of `epochs` and `steps`, positive".into(),
                ))
            }
        };
        if t.batch_size == 0 {
            return Err(bad("train.batch_size", "must be positive".into()));
        }
        let eval_batch_size = t.eval_batch_size.unwrap_or(t.batch_size);
        if eval_batch_size == 0 {
            return Err(bad("train.eval_batch_size", "must be positive".into()));
        }
        let depth_loss = match (self.task, t.loss) {
            (Task::Depth, None | Some(LossName::L1)) => DepthLoss::L1,
            (Task::Depth, Some(LossName::Berhu)) => DepthLoss::BerHu,
            (Task::Segmentation, None | Some(LossName::CrossEntropy)) => DepthLoss::L1,
            (task, Some(l)) => {
                return Err(bad(
                    "train.loss",
                    format!(
                        "`{}` is not a {} loss (depth: l1, berhu; segmentation: cross-entropy)",
                        serde_json::to_value(l)
                            .expect("enum")
                            .as_str()
                            .unwrap_or(""),
                        serde_json::to_value(task)
                            .expect("enum")
                            .as_str()
                            .unwrap_or("")
                    ),
                ))
            }
        };
        let task_metrics: Vec<Metric> = match self.task {
            Task::Depth => DEPTH_METRICS.to_vec(),
            Task::Segmentation => SEGMENTATION_METRICS.to_vec(),
        };
        let val_metric = match &t.val_metric {
            None => match self.task {
                Task::Depth => Metric::Rmse,
                Task::Segmentation => Metric::MIoU,
            },
            Some(s) => {
                let m = s
                    .parse::<Metric>()
                    .ok()
                    .filter(|m| *m == Metric::Loss || task_metrics.contains(m));
                m.ok_or_else(|| {
                    let mut names = vec!["loss"];
                    names.extend(task_metrics.iter().map(|m| m.name()));
                    let hint = suggest::nearest(s, &names)
                        .map(|b| format!("; did you mean `{b}`?"))
                        .unwrap_or_default();
                    bad(
                        "train.val_metric",
                        format!("`{s}` is not one of {}{hint}", names.join(", ")),
                    )
                })?
            }
        };
        for (f, v) in [
            ("train.val_every", t.val_every),
            ("train.log_every", t.log_every),
            ("train.checkpoint_every", t.checkpoint_every),
        ] {
            if v == Some(0) {
                return Err(bad(f, "must be positive".into()));
            }
        }
        let augment = match &t.augment {
            None => Augment::default(),
            Some(a) => {
                let jitter = match a.jitter {
                    None => None,
                    Some(j) if (0.0..1.0).contains(&j) => Some(ColorJitter {
                        brightness: j,
                        contrast: j,
                        saturation: j,
                    }),
                    Some(j) => {
                        return Err(bad(
                            "train.augment.jitter",
                            format!("must be in [0, 1), got {j}"),
                        ))
                    }
                };
                Augment {
                    hflip: a.hflip.unwrap_or(false),
                    jitter,
                }
            }
        };
        let radial_bins = t.radial_bins.unwrap_or(16);
        if radial_bins == 0 {
            return Err(bad("train.radial_bins", "must be positive".into()));
        }

        // Optimiser and schedule.
        let o = self.optimizer;
        if !(o.lr > 0.0 && o.lr.is_finite()) {
            return Err(bad(
                "optimizer.lr",
                format!("must be positive, got {}", o.lr),
            ));
        }
        let adam = AdamConfig {
            betas: o.betas.unwrap_or([0.9, 0.999]),
            eps: o.eps.unwrap_or(1e-8),
            weight_decay: o.weight_decay.unwrap_or(0.0),
            decoupled: o.kind == Some(OptimizerName::Adamw),
        };
        if !adam.betas.iter().all(|b| (0.0..1.0).contains(b)) {
            return Err(bad("optimizer.betas", "each must be in [0, 1)".into()));
        }
        if !positive(adam.eps) || adam.weight_decay.is_nan() || adam.weight_decay < 0.0 {
            return Err(bad(
                "optimizer",
                "eps must be positive and weight_decay non-negative".into(),
            ));
        }
        let schedule = match self.schedule {
            None => Schedule::constant(o.lr),
            Some(s) => {
                let unused = |key: &str, v: bool| -> Result<()> {
                    if v {
                        Err(bad(
                            &format!("schedule.{key}"),
                            format!("does not apply to kind = {:?}", s.kind),
                        ))
                    } else {
                        Ok(())
                    }
                };
                let decay = match s.kind {
                    ScheduleName::Constant => {
                        unused("every", s.every.is_some())?;
                        unused("gamma", s.gamma.is_some())?;
                        unused("min_lr", s.min_lr.is_some())?;
                        Decay::Constant
                    }
                    ScheduleName::Step => {
                        unused("min_lr", s.min_lr.is_some())?;
                        let every = s.every.filter(|&e| e > 0).ok_or_else(|| {
                            bad("schedule.every", "a positive step count is required".into())
                        })?;
                        let gamma = s.gamma.unwrap_or(0.1);
                        if !positive(gamma) {
                            return Err(bad("schedule.gamma", "must be positive".into()));
                        }
                        Decay::Step { every, gamma }
                    }
                    ScheduleName::Cosine => {
                        unused("every", s.every.is_some())?;
                        unused("gamma", s.gamma.is_some())?;
                        let min_lr = s.min_lr.unwrap_or(0.0);
                        if !(0.0..=o.lr).contains(&min_lr) {
                            return Err(bad(
                                "schedule.min_lr",
                                format!("must be in [0, lr = {}]", o.lr),
                            ));
                        }
                        Decay::Cosine { min_lr }
                    }
                };
                Schedule {
                    lr: o.lr,
                    warmup: s.warmup.unwrap_or(0),
                    decay,
                }
            }
        };

        // Output.
        let output = absolute(&self.output.unwrap_or_else(|| PathBuf::from(DEFAULT_OUTPUT)))?;
        let run_dir = output.join(&self.name);
        let init = init.map(|(name, file)| match file {
            Some(f) => InitSpec::Checkpoint(f),
            None => InitSpec::Experiment {
                checkpoints: layout::RunDir::new(output.join(&name)).checkpoints(),
                name,
            },
        });

        // Evaluations (default: the test split with the model's kernel).
        let mut raw_evals = self.evals;
        if raw_evals.is_empty() {
            if let Some(test) = raw_test {
                raw_evals.push(RawEval {
                    name: "test".into(),
                    data: test,
                    kernel: None,
                    camera: None,
                    padding: None,
                    size: None,
                    convention: None,
                    radial_bins: None,
                    radial_max: None,
                    images: None,
                    batch_size: None,
                });
            }
        }
        let mut evals = Vec::new();
        for (k, e) in raw_evals.into_iter().enumerate() {
            let f = |key: &str| format!("eval[{k}].{key}");
            let name = e.name;
            check_name(cfg, &f("name"), &name)?;
            if evals.iter().any(|e: &EvalSpec| e.name == name) {
                return Err(bad(&f("name"), format!("`{name}` is used twice")));
            }
            let data = e.data.resolve(cfg, &f("data"), root)?;
            let ek = e.kernel.unwrap_or(kernel);
            let einput = match (e.camera, e.padding, e.size, e.convention) {
                (None, None, None, None) => input.clone(),
                (cam, pad, size, conv) => {
                    // A camera of another image size gets its own defaults (no padding, its
                    // own size); the same camera, or one with the same image size, keeps the
                    // input's padding, and its size if the padding is kept too.
                    let cam_path = match cam {
                        Some(c) => absolute(&c)?,
                        None => input.camera_file.clone(),
                    };
                    let same = cam_path == input.camera_file
                        || camera::load(&cam_path).is_ok_and(|c| {
                            let s = width.map_or(1.0, |w| w as f64 / c.size()[0] as f64);
                            let scaled = c.rescaled([s, s], PixelConvention::HalfPixel);
                            scaled.size() == input.camera.size()
                        });
                    let size = size.or((same && pad.is_none()).then_some(input.size));
                    let pad = pad.or(same.then_some(input.padding));
                    input_spec(
                        cfg,
                        &f("camera"),
                        &cam_path,
                        width,
                        pad,
                        size,
                        conv.or(Some(input.convention)),
                    )?
                }
            };
            if ek == KernelName::Calibrated {
                check_calibrated(cfg, &f("size"), &model, &einput)?;
            }
            let radial_bins = e.radial_bins.unwrap_or(radial_bins);
            if radial_bins == 0 {
                return Err(bad(&f("radial_bins"), "must be positive".into()));
            }
            if let Some(r) = e.radial_max {
                if !positive(r) {
                    return Err(bad(&f("radial_max"), "must be positive".into()));
                }
            }
            let batch_size = e.batch_size.unwrap_or(eval_batch_size);
            if batch_size == 0 {
                return Err(bad(&f("batch_size"), "must be positive".into()));
            }
            evals.push(EvalSpec {
                name,
                data,
                kernel: ek,
                input: einput,
                radial_bins,
                radial_max: e.radial_max,
                images: e.images.unwrap_or(4),
                batch_size,
            });
        }

        Ok(Experiment {
            name: self.name,
            description: self.description,
            file: absolute(path)?,
            text: text.to_string(),
            seed: self.seed.unwrap_or(0),
            run_dir,
            output,
            device,
            model,
            kernel,
            init,
            input,
            train_data,
            val_data,
            test_data,
            train: TrainSpec {
                length,
                batch_size: t.batch_size,
                eval_batch_size,
                depth_loss,
                val_every: t.val_every,
                val_metric,
                log_every: t.log_every.unwrap_or(20),
                checkpoint_every: t.checkpoint_every,
                images: t.images.unwrap_or(4),
                radial_bins,
                augment,
                adam,
                schedule,
            },
            evals,
        })
    }
}

#[cfg(test)]
mod tests;
