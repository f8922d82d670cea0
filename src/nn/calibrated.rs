//! [`CalibratedConv2d`]: a deformable convolution whose offsets come from the camera.

use std::sync::Arc;

use tch::nn::{self, Module};
use tch::{Device, Kind, Tensor};

use crate::camera::{Camera, CameraModel};
use crate::error::{Error, Result};
use crate::kernel::{cached_offsets, InputFrame, LayerGeometry, Offsets};
use crate::ops::{
    deform_conv2d_planned, deform_conv2d_planned_as, layer_plan, Border, ConvGeometry, CpuLayout,
    SamplingPlan,
};

/// Output channels below which a CPU layer run with more than one thread returns NCHW rather than
/// channels-last: libtorch's channels-last batch norm (which follows every calibrated layer of the
/// U-Net) is several times slower with two threads than with one when a pixel's channels fill less
/// than a 64-byte cache line (fewer than 16 float32 values; the threads' partial sums seem to share
/// lines). Forward + backward of `BatchNorm2d` on `[8, C, H, W]` float32, torch 2.13 on a 2-core
/// Intel Xeon (`tools/bench_batch_norm_layouts.py`), NCHW / channels-last: 8 channels at 64x64 one
/// thread 0.76 / 0.67 ms, two threads 0.52 / 2.49 ms; at 128x128 1.29 / 10.3 ms (two threads); 16
/// channels at 128x128 2.81 / 2.19 ms, 32 at 16x16 0.10 / 0.11 ms. With one thread such layers stay
/// channels-last (no conversions; the quick sweep trains so). The values do not depend on the
/// layout; the batch norm's last bits may.
const NCHW_BELOW_CHANNELS: i64 = 16;

/// Geometry and bias of a convolution (pairs are `[y, x]`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Conv2dConfig {
    pub stride: [i64; 2],
    /// `None`: "same" padding `dilation * (k - 1) / 2`.
    pub padding: Option<[i64; 2]>,
    pub dilation: [i64; 2],
    pub groups: i64,
    pub bias: bool,
    /// Where the convolution sits in its network (read by [`super::ConvKind::CamConv`]).
    pub site: ConvSite,
    /// The pyramid level of its input feature map (0: the network input's resolution, `l`:
    /// `2^l` times smaller; read by [`super::ConvKind::CalibratedLearned`]).
    pub level: usize,
}

/// Where a convolution sits in its network: what a network tells the conv factory so that a
/// kind can treat some places differently without the network looking at the kind.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ConvSite {
    /// Anywhere else.
    #[default]
    Body,
    /// The first convolution after a decoder concatenates an encoder's skip connection (where
    /// CAM-Convs add their camera maps).
    AfterSkip,
}

impl Default for Conv2dConfig {
    fn default() -> Self {
        Conv2dConfig {
            stride: [1, 1],
            padding: None,
            dilation: [1, 1],
            groups: 1,
            bias: true,
            site: ConvSite::Body,
            level: 0,
        }
    }
}

impl Conv2dConfig {
    fn padding_for(&self, k: i64) -> [i64; 2] {
        self.padding.unwrap_or([
            self.dilation[0] * (k - 1) / 2,
            self.dilation[1] * (k - 1) / 2,
        ])
    }

    /// The equivalent tch config (same initialisation for both kinds).
    pub(crate) fn to_tch(self, k: i64) -> nn::ConvConfigND<[i64; 2]> {
        nn::ConvConfigND::<[i64; 2]> {
            stride: self.stride,
            padding: self.padding_for(k),
            dilation: self.dilation,
            groups: self.groups,
            bias: self.bias,
            ..Default::default()
        }
    }
}

/// The input feature map of a camera-dependent layer: the camera whose image it covers, how it
/// lies on that image (`frame`), and its size `[H, W]`.
#[derive(Clone, Copy, Debug)]
pub struct CameraInput<'a> {
    pub camera: &'a Camera,
    pub frame: &'a InputFrame,
    pub size: [i64; 2],
}

impl<'a> CameraInput<'a> {
    /// The feature map `size` `[H, W]` of `camera`'s image, placed on it by `frame`.
    pub fn new(camera: &'a Camera, frame: &'a InputFrame, size: [i64; 2]) -> Self {
        CameraInput {
            camera,
            frame,
            size,
        }
    }
}

/// The convolution's own parameters under `vs`: `weight` `[c_out, c_in / groups, k, k]` and, if
/// `cfg.bias`, `bias` `[c_out]`, with the same names, shapes and initialisation as tch's
/// `nn::conv2d` (so that a standard checkpoint loads into a calibrated layer unchanged).
pub(super) fn conv_parameters(
    vs: &nn::Path,
    c_in: i64,
    c_out: i64,
    k: i64,
    cfg: Conv2dConfig,
) -> (Tensor, Option<Tensor>) {
    let tch_cfg = cfg.to_tch(k);
    let ws = vs.var("weight", &[c_out, c_in / cfg.groups, k, k], tch_cfg.ws_init);
    let bs = cfg.bias.then(|| vs.var("bias", &[c_out], tch_cfg.bs_init));
    (ws, bs)
}

/// The calibrated offsets of a `k x k` layer of `cfg` (`c_in -> c_out`) on `input`, from the
/// process-wide cache, and the convolution geometry they are for.
///
/// # Errors
/// An even kernel size, groups that do not divide the channels, offsets that cannot be built.
pub(super) fn layer_offsets(
    c_in: i64,
    c_out: i64,
    k: i64,
    input: CameraInput<'_>,
    cfg: Conv2dConfig,
) -> Result<(Arc<Offsets>, ConvGeometry)> {
    if k < 1 || k % 2 == 0 {
        return Err(Error::InvalidArgument(format!(
            "calibrated kernels need an odd size, got {k}"
        )));
    }
    if cfg.groups < 1 || c_in % cfg.groups != 0 || c_out % cfg.groups != 0 {
        return Err(Error::InvalidArgument(format!(
            "groups = {} must divide C_in = {c_in} and C_out = {c_out}",
            cfg.groups
        )));
    }
    let padding = cfg.padding_for(k);
    let to_usize = |v: [i64; 2]| v.map(|x| x as usize);
    let geometry = LayerGeometry {
        kernel: [k as usize; 2],
        stride: to_usize(cfg.stride),
        padding: to_usize(padding),
        dilation: to_usize(cfg.dilation),
    };
    let offsets = cached_offsets(input.camera, to_usize(input.size), &geometry, input.frame)?;
    let conv = ConvGeometry::for_offsets(&offsets, cfg.stride, padding, cfg.dilation);
    Ok((offsets, conv))
}

/// A `k x k` deformable convolution with fixed, calibrated offsets.
///
/// On the CPU it works channels-last: the output is channels-last (same values and shape) for
/// any input layout, so that in a network of these layers the batch norm, ReLU and pooling after
/// one and the next one's input stay channels-last and nothing converts per call. An NCHW image
/// (at most 4 channels) is read as it is; a wider NCHW input is converted once. Code that needs
/// NCHW memory (`view` on an activation) calls `contiguous()`. With fewer than 16 outputs and
/// more than one libtorch thread the output is NCHW instead (`NCHW_BELOW_CHANNELS`).
///
/// Parameters are named and shaped exactly like tch's / PyTorch's `Conv2d` (`weight`, `bias`).
/// The sampling plan is built once per (offsets, geometry, device) and shared (same tensor
/// storage) by every layer with the same camera, feature-map size and geometry: offsets and
/// plans come from the process-wide caches [`crate::kernel::cached_offsets`] and
/// [`crate::ops::layer_plan`].
#[derive(Debug)]
pub struct CalibratedConv2d {
    pub ws: Tensor,
    pub bs: Option<Tensor>,
    pub offsets: Arc<Offsets>,
    plan: SamplingPlan,
    groups: i64,
}

impl CalibratedConv2d {
    /// Creates the layer under `vs` for the input feature map `input`.
    pub fn new(
        vs: &nn::Path,
        c_in: i64,
        c_out: i64,
        k: i64,
        input: CameraInput<'_>,
        cfg: Conv2dConfig,
    ) -> Result<Self> {
        let (offsets, conv) = layer_offsets(c_in, c_out, k, input, cfg)?;
        // A panorama's kernels continue across its left/right edge.
        let border = if input.camera.wraps_horizontally() {
            Border::WrapX
        } else {
            Border::Zeros
        };
        let plan = layer_plan(&offsets, conv, Kind::Float, border, vs.device())?;
        let (ws, bs) = conv_parameters(vs, c_in, c_out, k, cfg);
        Ok(CalibratedConv2d {
            ws,
            bs,
            offsets,
            plan,
            groups: cfg.groups,
        })
    }

    /// The layer's sampling plan.
    pub fn plan(&self) -> &SamplingPlan {
        &self.plan
    }

    /// Fallible forward.
    ///
    /// # Shapes
    /// - `xs`: `[B, C_in, H, W]` with `[H, W]` the size the layer was built for
    /// - output: `[B, C_out, H_out, W_out]`, channels-last in memory on the CPU (NCHW with fewer
    ///   than 16 outputs and more than one libtorch thread, see `NCHW_BELOW_CHANNELS`)
    pub fn f_forward(&self, xs: &Tensor) -> Result<Tensor> {
        if xs.device() != self.plan.device() {
            let plan = self.plan.to_device(xs.device());
            return deform_conv2d_planned(xs, &plan, &self.ws, self.bs.as_ref(), self.groups);
        }
        // On the CPU the layer works channels-last (its output, hence the batch norm and ReLU
        // after it and the next layer's input, stay channels-last): no layout conversion per
        // call, the network's NCHW image included (see `deform_conv2d_planned_as`).
        // But with fewer than NCHW_BELOW_CHANNELS outputs and more than one thread its output is
        // NCHW (see there).
        if xs.device() == Device::Cpu && xs.dim() == 4 {
            let layout = if self.ws.size()[0] < NCHW_BELOW_CHANNELS && tch::get_num_threads() > 1 {
                CpuLayout::Nchw
            } else {
                CpuLayout::ChannelsLast
            };
            let (ws, bs) = (&self.ws, self.bs.as_ref());
            return deform_conv2d_planned_as(xs, &self.plan, ws, bs, self.groups, layout);
        }
        deform_conv2d_planned(xs, &self.plan, &self.ws, self.bs.as_ref(), self.groups)
    }

    /// Device of the sampling plan.
    pub fn device(&self) -> Device {
        self.plan.device()
    }
}

impl Module for CalibratedConv2d {
    /// Panics with the message of [`CalibratedConv2d::f_forward`] on a wrong input size.
    fn forward(&self, xs: &Tensor) -> Tensor {
        self.f_forward(xs)
            .unwrap_or_else(|e| panic!("CalibratedConv2d: {e}"))
    }
}
