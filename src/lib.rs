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
//!   TOML files in `data/cameras/` or imported from other tools' calibrations. No tensors.
//! - [`kernel`]: the paper's "fisheye calibrated kernel" (Section 3.2): for a layer geometry and
//!   feature-map size, the offsets of every kernel tap relative to the regular deformable grid,
//!   in torchvision's layout, computed in parallel and cached. Tensors begin here.
//! - [`ops`]: the deformable convolution with fixed offsets, with torchvision `deform_conv2d`
//!   semantics, from a precomputed sampling plan: native C++ kernels on the CPU (a custom
//!   autograd function, within ~1.5x of `conv2d`), differentiable ATen ops elsewhere (CUDA).
//! - [`nn`]: layers: [`nn::CalibratedConv2d`] (same parameter names and shapes as a standard
//!   convolution) and the conv-kind factory the networks use.
//! - [`data`]: the data sets and the `Batch` / `BatchSource` contract training consumes.
//! - [`report`]: figures (the deformed-kernel grid of the paper's Figure 1a).
//! - [`io`]: atomic file output used by every writer.

pub mod camera;
pub mod data;
pub mod error;
pub mod io;
pub mod kernel;
pub mod nn;
pub mod ops;
pub mod report;

pub use error::{Error, Result};
