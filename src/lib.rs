//! # calibconv: calibrated convolutions for fisheye cameras
//!
//! Implements "Convolution kernel adaptation to calibrated fisheye" (Berenguel-Baeta et al.):
//! a camera calibration turns into fixed per-layer offsets of a deformable convolution so that
//! every kernel samples a perspective-like patch on the sphere.
//!
//! Data flows one way through the modules:
//!
//! - [`camera`]: camera models in plain `f64` Rust (Kannala-Brandt, pinhole, radial-tangential,
//!   double sphere, (extended) unified, Scaramuzza, equirectangular) behind one trait, read from
//!   TOML files in `data/cameras/` or imported from other tools' calibrations. Each model's file
//!   owns its camera-file schema and checks; constructors validate. No tensors.
//! - [`kernel`]: the paper's "fisheye calibrated kernel" (Section 3.2): for a layer geometry and
//!   feature-map size, the offsets of every kernel tap relative to the regular deformable grid,
//!   in torchvision's layout, computed in parallel and cached. Tensors begin here.
//! - [`ops`]: the deformable convolution with fixed offsets, with torchvision `deform_conv2d`
//!   semantics, from a precomputed (and cached) sampling plan: native C++ kernels on the CPU (a
//!   custom autograd function; 0.8-1.4x `conv2d` per layer and 1.0-1.1x a U-Net training step
//!   on one thread on an AMD Zen 4, 0.6-1.3x and 1.02-1.06x on an Intel Xeon, see the README's
//!   "Performance"), differentiable ATen ops elsewhere (CUDA, untested on hardware).
//! - [`nn`]: layers: [`nn::CalibratedConv2d`] (same parameter names and shapes as a standard
//!   convolution), the conv-kind factory the networks use, and [`nn::UNet`], the paper's
//!   network with milesial/Pytorch-UNet's parameter names (so PyTorch weights load by name and
//!   standard-kernel checkpoints load into calibrated networks unchanged).
//! - [`data`]: the [`data::Batch`] / [`data::BatchSource`] contract between data and training;
//!   procedural indoor panoramas, fisheye / perspective / rectified view synthesis, the
//!   Stanford 2D-3D-S loader, on-disk data sets and their prefetching loader; in-memory
//!   sources ([`data::memory`]) and a toy task ([`data::toy`]) for tests and smoke runs.
//! - [`loss`]: the training losses on valid pixels (depth L1 / BerHu, segmentation
//!   cross-entropy), which the trainer minimises and the evaluator reports.
//! - [`eval`]: the paper's metrics (depth MRE..delta3, segmentation
//!   mIoU / mAcc from one confusion matrix over the set; depth per image, the authors'
//!   convention, and pooled), radial bins around the principal point, prediction pictures, and
//!   the evaluator that writes `metrics.json` / `per_image.json` (typed records) and CSV.
//! - [`train`]: Adam with a savable state, learning-rate schedules, safetensors checkpoints
//!   with metadata (atomic, mismatches listed by name), and the trainer: periodic validation,
//!   best checkpoint, exact resume, stop on NaN / Inf. Output goes through the
//!   [`train::Reporter`] trait (TensorBoard event files, CSV logs).
//! - [`experiment`]: experiment TOML files (raw -> resolved, did-you-mean errors), the hook that
//!   opens data sources (data set folders whose camera matches, or the toy task), and the run
//!   directory (`experiment::layout`: its paths, typed records and lock): training then
//!   evaluations, as `calibconv train` / `calibconv eval` run them; profiles and `--set`
//!   overrides (TOML overlays) and sweeps over a folder with seeds as replicates, in dependency
//!   order (skip, resume, keep going past failures, SLURM scripts), as `calibconv sweep` runs
//!   them.
//! - [`report`]: figures (the deformed-kernel grid of the paper's Figure 1a, radial plots, point
//!   clouds) and the report of a
//!   sweep's results over seed replicates (the paper's tables with Student-t intervals over
//!   seeds, paired differences with a bootstrap over test images, radial plots, qualitative
//!   grids, the computed verdict on the paper's claims, the gain against the field of view,
//!   `REPORT.md`).
//! - [`bench`](mod@bench): the benchmark `calibconv bench` runs (paired, interleaved timings of the
//!   calibrated convolution against `conv2d`, and a peak-memory pass).
//! - [`device`]: what the process runs on (libtorch, its CUDA backend, GPUs, CPU kernels), as
//!   `calibconv info` prints it, and the check of an experiment's `device` field.
//! - [`io`]: atomic file output used by every writer.
//! - [`plots`]: line plots with bands (radial metrics, validation curves, the FOV gain), drawn
//!   by evaluations and reports alike.
//! - [`util`]: CSV number formatting and progress bars, shared by training, evaluation and
//!   reports.

pub mod bench;
pub mod camera;
pub mod data;
pub mod device;
pub mod error;
pub mod eval;
pub mod experiment;
pub mod io;
pub mod kernel;
pub mod loss;
pub mod nn;
pub mod ops;
pub mod plots;
pub mod report;
pub mod train;
pub mod util;

pub use error::{Error, Result};
