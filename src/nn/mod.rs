//! Layers: the calibrated convolution module and the conv-kind factory.
//!
//! The ablation axis of the paper (standard vs calibrated kernels) is one enum, [`ConvKind`],
//! read by one factory, [`conv2d`]; networks never branch on it. Both kinds create the same
//! parameters (`weight` `[C_out, C_in/groups, kh, kw]`, `bias` `[C_out]`) with the same
//! initialisation, so a checkpoint trained with standard kernels loads into a calibrated network
//! unchanged.
//!
//! [`unet`] is the paper's network (the classic U-Net with milesial/Pytorch-UNet's parameter
//! names), built from that factory.

mod calibrated;
pub mod unet;

pub use calibrated::{CalibratedConv2d, Conv2dConfig};
pub use unet::{Head, UNet, UNetConfig, UpMode};

use std::sync::Arc;

use tch::nn::{self, Module};
use tch::Tensor;

use crate::camera::Camera;
use crate::error::Result;
use crate::kernel::InputFrame;

/// Which convolution a network uses for its `k x k` (k > 1) convolutions.
#[derive(Clone, Debug, Default)]
pub enum ConvKind {
    /// Regular `conv2d`.
    #[default]
    Standard,
    /// Deformable convolution with offsets from the camera calibration (paper Section 3.2).
    Calibrated {
        camera: Arc<Camera>,
        frame: InputFrame,
    },
}

/// A convolution of either kind.
#[derive(Debug)]
pub enum Conv {
    Standard(nn::Conv2D),
    Calibrated(CalibratedConv2d),
}

impl Conv {
    /// The weight `[C_out, C_in/groups, kh, kw]`.
    pub fn weight(&self) -> &Tensor {
        match self {
            Conv::Standard(c) => &c.ws,
            Conv::Calibrated(c) => &c.ws,
        }
    }
}

impl Module for Conv {
    fn forward(&self, xs: &Tensor) -> Tensor {
        match self {
            Conv::Standard(c) => c.forward(xs),
            Conv::Calibrated(c) => c.forward(xs),
        }
    }
}

/// The conv factory: a `k x k` convolution of `kind` for an input feature map of `input_size`
/// `[H, W]` (needed by calibrated kernels only; 1x1 convolutions are always standard, they have
/// no spatial extent to calibrate).
pub fn conv2d(
    vs: &nn::Path,
    c_in: i64,
    c_out: i64,
    k: i64,
    kind: &ConvKind,
    input_size: [i64; 2],
    cfg: Conv2dConfig,
) -> Result<Conv> {
    match kind {
        ConvKind::Calibrated { camera, frame } if k > 1 => Ok(Conv::Calibrated(
            CalibratedConv2d::new(vs, c_in, c_out, k, camera, frame, input_size, cfg)?,
        )),
        _ => Ok(Conv::Standard(nn::conv(
            vs,
            c_in,
            c_out,
            [k, k],
            cfg.to_tch(k),
        ))),
    }
}

#[cfg(test)]
mod tests;
