//! Layers: the calibrated convolution module and the conv-kind factory.
//!
//! The ablation axis of the paper (standard vs calibrated kernels) is one enum, [`ConvKind`],
//! read by one factory, [`conv2d`]; networks never branch on it. Every kind creates the same
//! parameters (`weight` `[C_out, C_in/groups, kh, kw]`, `bias` `[C_out]`) with the same
//! initialisation, so a checkpoint trained with standard kernels loads into a calibrated network
//! unchanged. Kinds beyond the paper's two add parameters of their own under an `added` path
//! segment ([`is_added_parameter`]), zero-initialised so that the network starts as the one it
//! was loaded from: [`ConvKind::CamConv`] (CAM-Convs' camera maps at the skip connections,
//! [`CamMapsConv2d`]) and [`ConvKind::CalibratedLearned`] (calibrated offsets plus a learned
//! offset branch, [`LearnedOffsetConv2d`]). Networks tell the factory where a convolution sits
//! ([`ConvSite`]), never which kind it is.
//!
//! [`unet`] is the paper's network (the classic U-Net with milesial/Pytorch-UNet's parameter
//! names), built from that factory.

mod calibrated;
mod camconv;
mod learned;
pub mod unet;

pub use calibrated::{CalibratedConv2d, CameraInput, Conv2dConfig, ConvSite};
pub use camconv::CamMapsConv2d;
pub use learned::LearnedOffsetConv2d;
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
    /// Regular `conv2d`, plus CAM-Convs' camera maps (the pixel's ray, from the calibration)
    /// at the convolutions that read a skip connection ([`ConvSite::AfterSkip`]).
    CamConv {
        camera: Arc<Camera>,
        frame: InputFrame,
    },
    /// The calibrated offsets plus a learned, zero-initialised offset branch (DCN-style) in the
    /// layers at pyramid level [`LEARNED_FROM_LEVEL`] and deeper; calibrated kernels above.
    CalibratedLearned {
        camera: Arc<Camera>,
        frame: InputFrame,
    },
}

/// The shallowest pyramid level whose layers learn offsets under
/// [`ConvKind::CalibratedLearned`]. Deformable ConvNets put their learned offsets in the deep
/// stages only; here it is also what a CPU can afford: the sampled op rebuilds its columns every
/// call, and with every layer learning, a training step of the study's small U-Net (160x144,
/// batch 8, one thread) took 5.6x the calibrated step (1.7 against 9.4 images/s, loaded 2-core
/// machine). From level 2 (a quarter of the input's resolution) the layers that learn are those
/// of the two deepest levels of the study's depth-3 network.
pub const LEARNED_FROM_LEVEL: usize = 2;

/// The path segment under which a kind's own parameters live (`...0.added.cam_maps.weight`).
pub const ADDED: &str = "added";

/// Whether `name` (a var-store name, `a.b.c`) is a parameter that a [`ConvKind`] adds to the
/// network (absent from networks of the paper's two kinds; zero-initialised).
pub fn is_added_parameter(name: &str) -> bool {
    name.split('.').any(|segment| segment == ADDED)
}

/// A convolution of either kind.
#[derive(Debug)]
pub enum Conv {
    Standard(nn::Conv2D),
    Calibrated(CalibratedConv2d),
    CamMaps(CamMapsConv2d),
    Learned(LearnedOffsetConv2d),
}

impl Conv {
    /// The weight `[C_out, C_in/groups, kh, kw]`.
    pub fn weight(&self) -> &Tensor {
        match self {
            Conv::Standard(c) => &c.ws,
            Conv::Calibrated(c) => &c.ws,
            Conv::CamMaps(c) => &c.conv.ws,
            Conv::Learned(c) => &c.ws,
        }
    }
}

impl Module for Conv {
    fn forward(&self, xs: &Tensor) -> Tensor {
        match self {
            Conv::Standard(c) => c.forward(xs),
            Conv::Calibrated(c) => c.forward(xs),
            Conv::CamMaps(c) => c.forward(xs),
            Conv::Learned(c) => c.forward(xs),
        }
    }
}

/// The conv factory: a `k x k` convolution of `kind` for an input feature map of `input_size`
/// `[H, W]` (needed by the camera-dependent kinds only; 1x1 convolutions are always standard,
/// they have no spatial extent to calibrate). `cfg.site` says where the convolution sits
/// ([`ConvKind::CamConv`] adds its maps after skip connections only).
pub fn conv2d(
    vs: &nn::Path,
    c_in: i64,
    c_out: i64,
    k: i64,
    kind: &ConvKind,
    input_size: [i64; 2],
    cfg: Conv2dConfig,
) -> Result<Conv> {
    let input = |camera, frame| CameraInput::new(camera, frame, input_size);
    match kind {
        ConvKind::Calibrated { camera, frame } if k > 1 => Ok(Conv::Calibrated(
            CalibratedConv2d::new(vs, c_in, c_out, k, input(camera, frame), cfg)?,
        )),
        ConvKind::CalibratedLearned { camera, frame } if k > 1 => {
            let input = input(camera, frame);
            if cfg.level >= LEARNED_FROM_LEVEL {
                let conv = LearnedOffsetConv2d::new(vs, c_in, c_out, k, input, cfg)?;
                Ok(Conv::Learned(conv))
            } else {
                let conv = CalibratedConv2d::new(vs, c_in, c_out, k, input, cfg)?;
                Ok(Conv::Calibrated(conv))
            }
        }
        ConvKind::CamConv { camera, frame } if k > 1 && cfg.site == ConvSite::AfterSkip => {
            let input = input(camera, frame);
            Ok(Conv::CamMaps(CamMapsConv2d::new(
                vs, c_in, c_out, k, input, cfg,
            )?))
        }
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
