//! Figures people would rather look at than numbers.
//!
//! - [`kernels`]: the grid of calibrated kernels over a fisheye image (paper Figure 1a).

pub mod draw;
pub mod kernels;
pub mod plots;
