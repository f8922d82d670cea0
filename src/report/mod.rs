//! Figures people would rather look at than numbers.
//!
//! - [`kernels`]: the grid of calibrated kernels over a fisheye image (paper Figure 1a).
//! - [`tensorboard`], [`csv`]: training reporters ([`crate::train::Reporter`]): TensorBoard event
//!   files and per-split CSV logs.

pub mod csv;
pub mod draw;
pub mod kernels;
pub mod plots;
pub mod tensorboard;
