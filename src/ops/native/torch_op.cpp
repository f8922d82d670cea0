// The native kernels as PyTorch operators, for the Python package (calibconv.torch): not part of
// the Rust crate's build (build.rs compiles the other files); the package compiles this file
// with the others against the user's torch (python/calibconv/_extension.py) and registers
//
//   calibconv::deform_conv2d(input, weight, bias?, top_left, frac, rows, ho, wo, groups) -> out
//   calibconv::deform_conv2d_backward(grad, input, weight, top_left, frac, rows, ho, wo, groups,
//                                     has_bias, output_mask[3]) -> (grad_input, grad_weight,
//                                     grad_bias)
//
// for CPU tensors. The plan (top_left, frac, rows) is the one calibconv::ops builds, from the same
// code (calibconv_geometry::plan, through the PyO3 module): offsets shared by the batch, zeros
// outside. Autograd, the fake (meta) implementations for torch.compile, autocast and the ONNX
// translation are registered in Python (torch.library), so the forward and the backward are two
// operators a graph can hold, where the crate's DeformConv (deform.cpp) is one autograd Function.
// The passes are DeformConv's, chosen by the same rules, with one difference: nothing is kept
// from the forward for the backward but the inputs (autograd saves them), so a first layer's
// weight gradient gathers its columns again (three_channels layers: from the padded batch input,
// rebuilt, a copy of the image; other layers of <= 4 channels: tile by tile) instead of reading
// the forward's. Gradients not asked for in output_mask are returned as empty tensors.

#include <torch/library.h>

#include <array>
#include <optional>
#include <tuple>

#include "gather.h"

namespace calibconv::native {
namespace {

// The geometry of a call, after checking what the kernels rely on (the Python caller builds the
// plan for these shapes; a mismatch is an error here, not a read out of bounds).
Geo checked_geometry(const at::Tensor& input, const at::Tensor& weight, const at::Tensor& top_left,
                     const at::Tensor& frac, const at::Tensor& rows, int64_t ho, int64_t wo,
                     int64_t groups) {
  TORCH_CHECK(input.device().is_cpu() && weight.device().is_cpu(),
              "calibconv::deform_conv2d: CPU tensors only");
  TORCH_CHECK(input.dim() == 4 && weight.dim() == 4,
              "calibconv::deform_conv2d: input [B, C, H, W] and weight [C_out, C/G, kh, kw]");
  TORCH_CHECK(input.scalar_type() == at::kFloat || input.scalar_type() == at::kDouble,
              "calibconv::deform_conv2d: float32 or float64, got ", input.scalar_type());
  TORCH_CHECK(weight.scalar_type() == input.scalar_type() &&
                  frac.scalar_type() == input.scalar_type(),
              "calibconv::deform_conv2d: weight and plan fractions must be ", input.scalar_type());
  TORCH_CHECK(groups >= 1 && input.size(1) % groups == 0 && weight.size(0) % groups == 0 &&
                  weight.size(1) * groups == input.size(1),
              "calibconv::deform_conv2d: groups = ", groups, " does not fit input ",
              input.sizes(), " and weight ", weight.sizes());
  const Geo g = geometry(input, weight.size(0), weight.size(2) * weight.size(3), ho, wo, groups,
                         /*per_item=*/false, /*wrap=*/false);
  TORCH_CHECK(top_left.scalar_type() == at::kInt && top_left.is_contiguous() &&
                  top_left.numel() == g.P * g.K,
              "calibconv::deform_conv2d: top_left must be ", g.P * g.K, " contiguous int32");
  TORCH_CHECK(frac.is_contiguous() && frac.numel() == 2 * g.P * g.K,
              "calibconv::deform_conv2d: frac must be ", 2 * g.P * g.K, " contiguous values");
  TORCH_CHECK(rows.scalar_type() == at::kInt && rows.is_contiguous() && rows.numel() == 2 * g.Ho,
              "calibconv::deform_conv2d: rows must be [", g.Ho, ", 2] contiguous int32");
  return g;
}

at::Tensor deform_conv2d(const at::Tensor& input, const at::Tensor& weight,
                         const std::optional<at::Tensor>& bias, const at::Tensor& top_left,
                         const at::Tensor& frac, const at::Tensor& rows, int64_t ho, int64_t wo,
                         int64_t groups) {
  const Geo g = checked_geometry(input, weight, top_left, frac, rows, ho, wo, groups);
  const at::Tensor b = bias.has_value() ? *bias : at::Tensor();
  TORCH_CHECK(!b.defined() || (b.numel() == g.Cout && b.scalar_type() == input.scalar_type()),
              "calibconv::deform_conv2d: bias must be [", g.Cout, "] ", input.scalar_type());
  const at::Tensor coef = sample_coefficients(frac, g);
  const auto fmt = memory_format(input);
  if (three_channels(g, input.scalar_type() == at::kFloat)) {  // the batch at once
    at::Tensor padded;
    return forward_batch(g, input, weight, b, top_left, coef, fmt, &padded);
  }
  at::Tensor out;
  AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "calibconv_deform_forward", [&] {
    out = forward_impl<scalar_t>(g, input, weight, b, top_left, coef, rows, at::Tensor(), fmt);
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> deform_conv2d_backward(
    const at::Tensor& grad, const at::Tensor& input, const at::Tensor& weight,
    const at::Tensor& top_left, const at::Tensor& frac, const at::Tensor& rows, int64_t ho,
    int64_t wo, int64_t groups, bool has_bias, std::array<bool, 3> mask) {
  const Geo g = checked_geometry(input, weight, top_left, frac, rows, ho, wo, groups);
  TORCH_CHECK(grad.dim() == 4 && grad.size(0) == g.B && grad.size(1) == g.Cout &&
                  grad.size(2) == g.Ho && grad.size(3) == g.Wo &&
                  grad.scalar_type() == input.scalar_type(),
              "calibconv::deform_conv2d_backward: grad must be [", g.B, ", ", g.Cout, ", ", g.Ho,
              ", ", g.Wo, "] ", input.scalar_type(), ", got ", grad.sizes());
  // The output gradient is read in place if it is NCHW- or channels-last-contiguous.
  at::Tensor gy = grad;
  if (!gy.is_contiguous() && !gy.is_contiguous(at::MemoryFormat::ChannelsLast)) {
    gy = gy.contiguous(memory_format(input));
  }
  at::Tensor gx, gw, gb;
  const at::Tensor coef = sample_coefficients(frac, g);
  const bool bias_grad = has_bias && mask[2];
  AT_DISPATCH_FLOATING_TYPES(input.scalar_type(), "calibconv_deform_backward", [&] {
    const bool is_float = std::is_same_v<scalar_t, float>;
    if (mask[1] && !mask[0] && three_channels(g, is_float)) {
      // a first layer: its columns gathered again from the padded batch input (the tensor the
      // forward's forward_batch made, rebuilt; grad_weight_first)
      gw = grad_weight_first(g, padded_batch_input(input, g), /*batched=*/true, gy, top_left,
                             coef)
               .view(weight.sizes());
    } else if (mask[1]) {
      auto [w, b] = grad_weight_impl<scalar_t>(g, input, gy, top_left, coef, rows, at::Tensor(),
                                               bias_grad);
      gw = w.view(weight.sizes());
      gb = b;  // (undefined where the weight gradient did not sum it)
    }
    if (mask[0]) {
      gx = grad_input_impl<scalar_t>(g, input, pack_weight(weight, g), gy, top_left, coef, rows);
    }
  });
  if (bias_grad && !gb.defined()) gb = gy.sum({0, 2, 3});
  const auto none = [&] { return at::empty({0}, input.options()); };
  return {gx.defined() ? gx : none(), gw.defined() ? gw : none(), gb.defined() ? gb : none()};
}

}  // namespace
}  // namespace calibconv::native

TORCH_LIBRARY(calibconv, m) {
  m.def(
      "deform_conv2d(Tensor input, Tensor weight, Tensor? bias, Tensor top_left, Tensor frac, "
      "Tensor rows, int ho, int wo, int groups) -> Tensor");
  m.def(
      "deform_conv2d_backward(Tensor grad, Tensor input, Tensor weight, Tensor top_left, "
      "Tensor frac, Tensor rows, int ho, int wo, int groups, bool has_bias, bool[3] output_mask) "
      "-> (Tensor, Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(calibconv, CPU, m) {
  m.impl("deform_conv2d", &calibconv::native::deform_conv2d);
  m.impl("deform_conv2d_backward", &calibconv::native::deform_conv2d_backward);
}
