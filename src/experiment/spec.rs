//! The resolved experiment: [`Experiment`] and its parts, every value checked and every default
//! filled in (made by [`super::RawExperiment::resolve`]); serialised into the run directory as
//! the record of what ran.

use std::path::PathBuf;
use std::sync::Arc;

use serde::Serialize;
use tch::Device;

use super::{KernelName, SourceSpec};
use crate::camera::{Camera, PixelConvention};
use crate::data::loader::Augment;
use crate::error::Result;
use crate::eval::metrics::Metric;
use crate::kernel::InputFrame;
use crate::loss::DepthLoss;
use crate::nn::{ConvKind, UNetConfig};
use crate::train::adam::AdamConfig;
use crate::train::schedule::Schedule;
use crate::train::Length;

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
            KernelName::CamConv => ConvKind::CamConv {
                camera: self.camera.clone(),
                frame: self.frame(),
            },
            KernelName::CalibratedLearned => ConvKind::CalibratedLearned {
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
    /// The device named by `device`, checked against this process (`cuda` without CUDA is an
    /// error naming the file and the field: see [`crate::device::resolve`]).
    pub fn device(&self) -> Result<Device> {
        crate::device::resolve(&self.device, &self.file, "device")
    }
}

pub use crate::device::parse as parse_device;
