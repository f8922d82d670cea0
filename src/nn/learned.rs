//! [`LearnedOffsetConv2d`]: calibrated offsets that keep learning (DCN-style, Dai et al. 2017).
//!
//! The layer samples at the calibrated offsets plus the output of an offset branch: a `k x k`
//! convolution of the layer's input (same stride, padding and dilation) with `2*k*k` outputs,
//! the pair `(dy, dx)` per tap and output pixel, as in deformable ConvNets. The branch is
//! zero-initialised (weight and bias), so the layer starts as the calibrated layer and the
//! fine-tuning moves the sampling where the loss asks. Its parameters live under
//! `added.offsets.{weight,bias}`; the convolution's own `weight` / `bias` keep the names and
//! shapes of [`super::CalibratedConv2d`], so a standard or calibrated checkpoint loads unchanged.
//!
//! Sampling goes through [`crate::ops::f_deform_conv2d_sampled`] (differentiable in the offsets,
//! zeros outside the input). Cameras whose kernels wrap across the image's left/right edge
//! (panoramas) are refused: that op has no circular border.

use tch::nn::{self, Module};
use tch::Tensor;

use super::calibrated::{conv_parameters, layer_offsets};
use super::{CameraInput, Conv2dConfig};
use crate::camera::CameraModel;
use crate::error::{Error, Result};
use crate::kernel::OffsetsTensor;
use crate::ops::{f_deform_conv2d_sampled, ConvGeometry};

/// A `k x k` deformable convolution at calibrated offsets plus learned ones.
#[derive(Debug)]
pub struct LearnedOffsetConv2d {
    pub ws: Tensor,
    pub bs: Option<Tensor>,
    /// The offset branch (`2*k*k` outputs), zero at construction.
    pub offsets: nn::Conv2D,
    /// The calibrated offsets `[1, 2*k*k, H_out, W_out]` (constant).
    calibrated: Tensor,
    geometry: ConvGeometry,
    groups: i64,
}

impl LearnedOffsetConv2d {
    /// Creates the layer under `vs` for the input feature map `input`.
    pub fn new(
        vs: &nn::Path,
        c_in: i64,
        c_out: i64,
        k: i64,
        input: CameraInput<'_>,
        cfg: Conv2dConfig,
    ) -> Result<Self> {
        if input.camera.wraps_horizontally() {
            return Err(Error::InvalidArgument(format!(
                "learned offsets need a camera whose kernels do not wrap around the image \
                 ({} does: a panorama)",
                input.camera.model_name()
            )));
        }
        let (calibrated, geometry) = layer_offsets(c_in, c_out, k, input, cfg)?;
        let tch_cfg = cfg.to_tch(k);
        let calibrated = calibrated.to_tensor().unsqueeze(0).to_device(vs.device());
        let (ws, bs) = conv_parameters(vs, c_in, c_out, k, cfg);
        let offsets = nn::conv(
            vs / super::ADDED / "offsets",
            c_in,
            2 * k * k,
            [k, k],
            nn::ConvConfigND::<[i64; 2]> {
                ws_init: nn::Init::Const(0.0),
                bs_init: nn::Init::Const(0.0),
                groups: 1,
                ..tch_cfg
            },
        );
        Ok(LearnedOffsetConv2d {
            ws,
            bs,
            offsets,
            calibrated,
            geometry,
            groups: cfg.groups,
        })
    }

    /// Fallible forward.
    ///
    /// # Shapes
    /// - `xs`: `[B, C_in, H, W]` with `[H, W]` the size the layer was built for
    /// - output: `[B, C_out, H_out, W_out]`
    pub fn f_forward(&self, xs: &Tensor) -> Result<Tensor> {
        let learned = self.offsets.forward(xs);
        let offsets = learned + self.calibrated.to_kind(xs.kind());
        f_deform_conv2d_sampled(
            xs,
            &offsets,
            &self.ws,
            self.bs.as_ref(),
            self.geometry,
            self.groups,
        )
    }
}

impl Module for LearnedOffsetConv2d {
    /// Panics with the message of [`LearnedOffsetConv2d::f_forward`] on a wrong input size.
    fn forward(&self, xs: &Tensor) -> Tensor {
        self.f_forward(xs)
            .unwrap_or_else(|e| panic!("LearnedOffsetConv2d: {e}"))
    }
}
