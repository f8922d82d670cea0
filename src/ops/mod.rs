//! The deformable convolution with fixed offsets, with torchvision `deform_conv2d` semantics.
//!
//! # Sampling plan
//! Offsets are data, not parameters, so all sampling is precomputed once per layer into a
//! [`SamplingPlan`]: for every (output pixel, tap) the index (int32) of its top-left bilinear
//! corner in the input padded by one row above, two below and a column on each side, and the
//! fractional parts `(ly, lx)` of the sample position (12 bytes a float32 sample). In the padded
//! input the four corners are always neighbours, and torchvision's "zeros outside" (a location
//! with `y <= -1`, `y >= H`, `x <= -1` or `x >= W` samples 0, and each out-of-range corner
//! contributes 0) is the padding's zeros: corners off the input land in it, and samples wholly
//! outside point at an all-zero block; [`Border::WrapX`] instead takes columns modulo `W` (the
//! right padding column then holds the first column). The corner weights
//! `(1-ly)(1-lx), (1-ly)lx, ly(1-lx), ly lx` do not depend on the border rule, which only moves
//! corners, so every kernel consumes any plan unchanged. The ATen path reads the four corners as
//! flat indices into the unpadded input with an extra zero row ([`SamplingPlan::corner_index`]).
//! The plan also records, per output row, the input rows its samples read (the scatter's
//! schedule). Plans are built in parallel over output rows, written in place.
//!
//! # Two implementations, one semantics ([`Backend`])
//! - **Native CPU kernels** (`native/`, C++ compiled by `build.rs` against libtorch; the default
//!   for CPU tensors): a `torch::autograd::Function`. The forward gathers column tiles `[T, K*C]`
//!   over the flattened `(item, pixel)` rows from the input padded channels-last (each thread pads
//!   the rows its tiles read) and multiplies them by the packed weight; the weight gradient
//!   gathers the tiles again (a first layer of <= 4 channels keeps its columns instead); the input
//!   gradient scatters `gy @ W` to the corners in bands of output rows whose input rows are
//!   disjoint within each of two phases: no atomics, and a summation order that does not depend
//!   on the number of threads. Products go through the BLAS (`at::mm`; oneDNN when asked, see
//!   [`GemmLibrary`]) or, for few output channels (float32, one group, 8 to 1024 outputs on
//!   AVX-512, 8 to 32 on AVX2), through register-blocked kernels on L1-sized blocks of pixels,
//!   compiled per instruction-set level and picked at run time ([`SmallKernelIsa`]; both levels
//!   give identical values; large weights on Intel CPUs with MKL: [`LargeWeights`]). Float32 and
//!   float64; no double backward (an error, not a wrong result); C++ exceptions come back as
//!   [`Error::Torch`], never across the FFI boundary. The design of each pass is in the comments
//!   of `native/deform.cpp`; what was measured for its choices is in docs/bench/cpu-kernels.md.
//! - **ATen composition** (any device; the CUDA path): one `embedding_bag` (weighted sum of the
//!   four corner rows of a pixel-major table) builds the column matrix `[B, P, K*C]`, and one
//!   batched `matmul` applies the weight; libtorch differentiates both.
//!
//! # Numerics
//! Both compute torchvision's bilinear deformable convolution; they differ from each other (and
//! from torchvision) only in rounding: summation order (per-tile GEMMs, per-chunk weight
//! gradients, the scatter order, the BLAS's blocking in float32), fused multiply-adds in the
//! gathers, and, for float32 plans, corner weights formed in float32 from float32 fractions
//! (relative differences ~1e-7). Tests hold the native path to the ATen one at 1e-12 (float64)
//! on random plans with out-of-range and far-reaching samples, to torchvision's fixtures at 1e-4
//! (float32) / 1e-6 (float64), and to finite differences in float64. Gradients with respect to
//! the offsets are not computed (they are fixed data); offsets that learn go through
//! [`f_deform_conv2d_sampled`] (module `sampled`: ATen's `grid_sampler_2d`, differentiable in
//! the offsets, no plan).
//!
//! Shared offsets `[2*kh*kw, H_out, W_out]` are used by every batch item without copying;
//! per-item offsets `[B, 2*kh*kw, H_out, W_out]` are supported too.
//!
//! # Plan cache
//! [`deform_conv2d`] takes its plan from [`tensor_plan`] (the same offsets tensor, unchanged,
//! is planned once); layers take theirs from [`layer_plan`]. Both live in one cache (module
//! `cache`, its docs give the keys and lifetimes); [`clear_plan_caches`] empties it.

mod cache;
#[cfg(calibconv_native)]
mod native;
/// Without the native kernels their settings are fixed: there is nothing to choose.
#[cfg(not(calibconv_native))]
mod native {
    use super::settings::sealed::Entry;
    pub(super) fn setting(_entry: Entry, _choice: Option<Option<i32>>) -> Option<i32> {
        None
    }
}
mod plan;
mod sampled;
mod settings;

pub use cache::{clear_plan_caches, layer_plan, tensor_plan, TENSOR_PLANS};
pub use plan::{Border, ConvGeometry, SamplingPlan};
pub use sampled::f_deform_conv2d_sampled;
pub use settings::{GemmLibrary, LargeWeights, NativeSetting, SmallKernelIsa};

use tch::{Kind, Tensor};

use crate::error::{Error, Result};

/// Deformable 2-D convolution with torchvision semantics (one offset group, no mask).
///
/// # Shapes
/// - `input`: `[B, C_in, H, W]`, float32 or float64
/// - `offsets`: `[2*kh*kw, H_out, W_out]` (shared by the batch) or `[B, 2*kh*kw, H_out, W_out]`,
///   per tap (row-major) the pair `(dy, dx)`
/// - `weight`: `[C_out, C_in / groups, kh, kw]`; `bias`: `[C_out]`
/// - output: `[B, C_out, H_out, W_out]`
///
/// # Panics
/// On invalid shapes or kinds, with the message of [`f_deform_conv2d`].
#[allow(clippy::too_many_arguments)]
pub fn deform_conv2d(
    input: &Tensor,
    offsets: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    stride: [i64; 2],
    padding: [i64; 2],
    dilation: [i64; 2],
    groups: i64,
) -> Tensor {
    f_deform_conv2d(
        input, offsets, weight, bias, stride, padding, dilation, groups,
    )
    .unwrap_or_else(|e| panic!("deform_conv2d: {e}"))
}

/// Fallible twin of [`deform_conv2d`]. The sampling plan comes from the plan cache
/// ([`tensor_plan`]): a loop that calls this again and again with the same offsets tensor builds
/// it once (the cache keys it by the tensor's storage, shape, strides and version counter, so an
/// in-place change of the offsets builds a new one). Layers hold their own [`SamplingPlan`] and
/// call [`deform_conv2d_planned`].
#[allow(clippy::too_many_arguments)]
pub fn f_deform_conv2d(
    input: &Tensor,
    offsets: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    stride: [i64; 2],
    padding: [i64; 2],
    dilation: [i64; 2],
    groups: i64,
) -> Result<Tensor> {
    let (_, _, h, w) = size4(input, "input", INPUT_DIMS)?;
    let (_, _, kh, kw) = size4(weight, "weight", WEIGHT_DIMS)?;
    let plan = tensor_plan(
        offsets,
        [h, w],
        ConvGeometry::new([kh, kw], stride, padding, dilation),
        input.kind(),
        input.device(),
    )?;
    deform_conv2d_planned(input, &plan, weight, bias, groups)
}

/// Which implementation runs the convolution.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Backend {
    /// The native kernels for CPU tensors (when built, see `build.rs`), the ATen composition
    /// on other devices.
    #[default]
    Auto,
    /// The composition of device-generic ATen ops, on any device.
    Aten,
}

/// Whether the native CPU kernels were compiled into this build.
pub fn native_available() -> bool {
    cfg!(calibconv_native)
}

/// The deformable convolution through a prebuilt plan (see [`f_deform_conv2d`] for shapes).
pub fn deform_conv2d_planned(
    input: &Tensor,
    plan: &SamplingPlan,
    weight: &Tensor,
    bias: Option<&Tensor>,
    groups: i64,
) -> Result<Tensor> {
    deform_conv2d_planned_with(input, plan, weight, bias, groups, Backend::Auto)
}

/// [`deform_conv2d_planned`] with a chosen implementation. Both give the same result up to
/// floating-point rounding (summation order).
pub fn deform_conv2d_planned_with(
    input: &Tensor,
    plan: &SamplingPlan,
    weight: &Tensor,
    bias: Option<&Tensor>,
    groups: i64,
    backend: Backend,
) -> Result<Tensor> {
    PlannedCall::checked(input, plan, weight, bias, groups)?.run(backend)
}

/// The layout of a calibrated layer's output on the CPU ([`deform_conv2d_planned_as`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum CpuLayout {
    /// Channels-last: the calibrated layer's contract (`nn::CalibratedConv2d`: its output, hence
    /// the batch norm and ReLU after it and the next layer's input, stay channels-last).
    ChannelsLast,
    /// NCHW: the layer's output with few channels at more than one thread (see
    /// `nn::CalibratedConv2d`).
    Nchw,
}

/// [`deform_conv2d_planned`] with its output in `layout` for an input of any layout.
/// Channels-last: an NCHW input of at most 4 channels (a first layer's image) goes to the native
/// kernels as it is: they read it into their padded channels-last copy directly and write the
/// output channels-last, so no converted copy of the image is made per call. Wider NCHW inputs
/// are converted first (the backward pass then reads and returns channels-last tensors), as is
/// every input of the ATen composition. NCHW: the native kernels write it from either input
/// layout (a conversion after the op cost a copy of the output forward and one of its gradient
/// backward); the ATen composition's output is made contiguous.
pub(crate) fn deform_conv2d_planned_as(
    input: &Tensor,
    plan: &SamplingPlan,
    weight: &Tensor,
    bias: Option<&Tensor>,
    groups: i64,
    layout: CpuLayout,
) -> Result<Tensor> {
    let call = PlannedCall::checked(input, plan, weight, bias, groups)?;
    let image = input.size()[1] <= 4;
    #[cfg(calibconv_native)]
    if input.device() == tch::Device::Cpu && (image || layout == CpuLayout::Nchw) {
        let out = match layout {
            CpuLayout::ChannelsLast => native::OutLayout::ChannelsLast,
            CpuLayout::Nchw => native::OutLayout::Nchw,
        };
        return native::deform_conv2d_cpu(&call, out);
    }
    let _ = image;
    match layout {
        CpuLayout::ChannelsLast => {
            // The same operands in another memory layout: still checked.
            let input = channels_last(input);
            PlannedCall {
                input: &input,
                ..call
            }
            .run(Backend::Auto)
        }
        CpuLayout::Nchw => Ok(call.run(Backend::Auto)?.contiguous()),
    }
}

/// `x` `[B, C, H, W]` as a channels-last tensor (itself, as a view, if it already is one).
fn channels_last(x: &Tensor) -> Tensor {
    x.permute([0, 2, 3, 1]).contiguous().permute([0, 3, 1, 2])
}

/// The operands of a planned call, checked: shapes, kinds, devices and groups fit
/// ([`PlannedCall::checked`]), so either implementation can take them as they are.
#[derive(Clone, Copy)]
struct PlannedCall<'a> {
    input: &'a Tensor,
    plan: &'a SamplingPlan,
    weight: &'a Tensor,
    bias: Option<&'a Tensor>,
    groups: i64,
}

impl<'a> PlannedCall<'a> {
    /// The operands of [`deform_conv2d_planned`], once they are checked.
    fn checked(
        input: &'a Tensor,
        plan: &'a SamplingPlan,
        weight: &'a Tensor,
        bias: Option<&'a Tensor>,
        groups: i64,
    ) -> Result<Self> {
        let (_, c, _, _) = plan.check_input(input)?;
        let (c_out, c_per_group, kh, kw) = size4(weight, "weight", WEIGHT_DIMS)?;
        if [kh, kw] != plan.kernel() {
            return Err(Error::InvalidArgument(format!(
                "weight kernel {kh}x{kw} does not match the plan's {:?}",
                plan.kernel()
            )));
        }
        if !groups_fit(groups, c, c_out, c_per_group) {
            return Err(Error::InvalidArgument(format!(
                "groups = {groups} does not fit input channels {c}, weight {:?}",
                weight.size()
            )));
        }
        let same = |t: &Tensor| t.kind() == input.kind() && t.device() == input.device();
        if !same(weight) {
            return Err(Error::InvalidArgument(format!(
                "weight is {:?} on {:?} but input is {:?} on {:?}",
                weight.kind(),
                weight.device(),
                input.kind(),
                input.device()
            )));
        }
        if let Some(bias) = bias {
            if bias.size() != [c_out] || !same(bias) {
                return Err(Error::InvalidArgument(format!(
                    "bias must be [{c_out}] {:?} on {:?}, got {:?} {:?} on {:?}",
                    input.kind(),
                    input.device(),
                    bias.size(),
                    bias.kind(),
                    bias.device()
                )));
            }
        }
        Ok(PlannedCall {
            input,
            plan,
            weight,
            bias,
            groups,
        })
    }

    /// The convolution through `backend` (output in the input's layout).
    fn run(self, backend: Backend) -> Result<Tensor> {
        #[cfg(calibconv_native)]
        if backend == Backend::Auto && self.input.device() == tch::Device::Cpu {
            return native::deform_conv2d_cpu(&self, native::OutLayout::Input);
        }
        let _ = backend;
        self.aten()
    }

    /// The ATen composition: columns by `embedding_bag`, then one batched `matmul`.
    fn aten(self) -> Result<Tensor> {
        let cols = self.plan.f_columns(self.input)?; // [B, P, K, C]
        let (b, p, taps, _) = cols.size4()?;
        let (c_out, c_per_group, _, _) = self.weight.size4()?;
        let [ho, wo] = self.plan.output_size();
        let (g, c_out_g) = (self.groups, c_out / self.groups);
        // Columns [B, G, P, K*Cg] against weights [G, K*Cg, C_out/G], both tap-major then channel.
        let cols = cols
            .f_view([b, p, taps, g, c_per_group])?
            .f_permute([0, 3, 1, 2, 4])?
            .f_reshape([b, g, p, taps * c_per_group])?;
        let w = self
            .weight
            .f_view([g, c_out_g, c_per_group, taps])?
            .f_permute([0, 3, 2, 1])?
            .f_reshape([g, taps * c_per_group, c_out_g])?;
        // [B, G, P, C_out/G] -> [B, C_out, H_out, W_out]
        let mut out = cols
            .f_matmul(&w)?
            .f_permute([0, 1, 3, 2])?
            .f_reshape([b, c_out, ho, wo])?;
        if let Some(bias) = self.bias {
            out = out.f_add(&bias.view([1, c_out, 1, 1]))?;
        }
        Ok(out)
    }
}

/// The layout of an input, as [`size4`] names it.
const INPUT_DIMS: &str = "[B, C, H, W]";
/// The layout of a weight, as [`size4`] names it.
const WEIGHT_DIMS: &str = "[C_out, C_in/groups, kh, kw]";

/// The four sizes of `t`, or an error saying that `name` must be `dims`.
fn size4(t: &Tensor, name: &str, dims: &str) -> Result<(i64, i64, i64, i64)> {
    t.size4()
        .map_err(|_| Error::InvalidArgument(format!("{name} must be {dims}, got {:?}", t.size())))
}

/// Whether `groups` fits `c_in` input and `c_out` output channels and a weight of `c_per_group`
/// input channels (`[c_out, c_per_group, kh, kw]`).
fn groups_fit(groups: i64, c_in: i64, c_out: i64, c_per_group: i64) -> bool {
    groups >= 1 && c_in % groups == 0 && c_out % groups == 0 && c_per_group * groups == c_in
}

/// Checks that a tensor is floating point (float32 or float64).
fn check_float(t: &Tensor, what: &str) -> Result<()> {
    match t.kind() {
        Kind::Float | Kind::Double => Ok(()),
        k => Err(Error::InvalidArgument(format!(
            "{what} must be float32 or float64, got {k:?}"
        ))),
    }
}

#[cfg(test)]
mod tests;
