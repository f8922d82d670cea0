//! The experiment file as written: the `Raw*` tables (serde, `deny_unknown_fields`), the enums
//! spelt in the file, and [`parse`], whose errors name the misspelt key and suggest the nearest
//! valid one.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::suggest;
use crate::camera::PixelConvention;
use crate::error::{Error, Result};
use crate::nn::UpMode;

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
    /// Standard kernels plus CAM-Convs' camera maps at the skip connections.
    #[serde(rename = "camconv")]
    CamConv,
    /// Calibrated offsets plus a learned offset branch.
    CalibratedLearned,
}

impl KernelName {
    /// Every kernel name, in the order tables list them.
    pub const ALL: [KernelName; 4] = [
        KernelName::Standard,
        KernelName::Calibrated,
        KernelName::CamConv,
        KernelName::CalibratedLearned,
    ];

    /// `standard`, `calibrated`, `camconv` or `calibrated-learned`.
    pub fn as_str(&self) -> &'static str {
        match self {
            KernelName::Standard => "standard",
            KernelName::Calibrated => "calibrated",
            KernelName::CamConv => "camconv",
            KernelName::CalibratedLearned => "calibrated-learned",
        }
    }

    /// Whether the kind reads the camera calibration (all but `standard`).
    pub fn uses_camera(&self) -> bool {
        *self != KernelName::Standard
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
    /// Train on this fraction of the split's samples only, `(0, 1]` (data sets only): a subset
    /// drawn with the experiment's seed, nested across fractions (see
    /// [`crate::data::loader::Dataset::keep_fraction`]).
    pub fraction: Option<f64>,
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
