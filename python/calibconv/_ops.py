"""``torch.ops.calibconv.deform_conv2d``: the native CPU kernels as a custom operator.

The operators are C++ (``src/ops/native/torch_op.cpp``, compiled by :mod:`._extension`); this
module registers what torch needs around them, with ``torch.library``:

- autograd: the backward is the operator ``calibconv::deform_conv2d_backward`` (input, weight
  and bias gradients, those not needed skipped); no double backward;
- fake (meta) implementations of both, so that ``torch.compile`` and ``torch.export`` trace a
  calibrated layer as one opaque node, forward and backward;
- autocast on the CPU: float16 / bfloat16 inputs are computed in float32 (the kernels are float32
  and float64; the output is float32, as torchvision's ``deform_conv2d`` under autocast).

:class:`Plan` holds a layer's sampling plan, built once from its offsets by
:func:`calibconv._native.sampling_plan` (the Rust crate's plan code).
"""

from __future__ import annotations

import warnings
from typing import Optional, Tuple

import numpy as np
import torch
from torch import Tensor

from . import _extension

_registered = False
_warned = False


def available() -> bool:
    """Whether the native operators are loaded (building them at the first call)."""
    global _registered
    if _registered:
        return True
    if _extension.load() is not None:
        return False
    _register()
    _registered = True
    return True


def fallback_reason() -> Optional[str]:
    """Why the native operators are not used (``None`` when they are)."""
    return None if available() else _extension.load()


def warn_fallback() -> None:
    """The one warning of a process that runs torchvision's op on the CPU instead."""
    global _warned
    reason = _extension.load()
    if _warned or reason is None or reason == "CALIBCONV_NATIVE=0":
        return
    _warned = True
    warnings.warn(
        f"calibconv: the native CPU kernels are not available ({reason}); calibrated layers on "
        f"the CPU run torchvision's deform_conv2d instead, which rebuilds the sampling on every "
        f"call: 4-7x the standard model's time in inference and 8-24x for a training step "
        f"(resnet18, 224x256), against about 1x with the native kernels. Install a C++17 "
        f"compiler (g++ or clang++, or set CXX) and restart to build them.",
        RuntimeWarning,
        stacklevel=3,
    )


class Plan:
    """A layer's sampling plan on the CPU: ``top_left`` int32 ``[N]``, the fractions ``frac``
    ``[2 N]`` in float64 and float32 (rounded from the float64 ones, as the Rust crate's float32
    plans), ``rows`` int32 ``[H_out, 2]``, for ``N = H_out * W_out * kh * kw`` samples."""

    def __init__(self, offsets: np.ndarray, input_size, kernel, stride, padding, dilation):
        from ._native import sampling_plan

        tl, frac, rows = sampling_plan(np.asarray(offsets, dtype=np.float32), tuple(input_size),
                                       tuple(kernel), tuple(stride), tuple(padding),
                                       tuple(dilation))
        self.top_left = torch.from_numpy(tl)
        self.frac64 = torch.from_numpy(frac)
        self.frac32 = self.frac64.float()
        self.rows = torch.from_numpy(rows)
        self.output_size: Tuple[int, int] = (int(offsets.shape[-2]), int(offsets.shape[-1]))

    def frac(self, dtype: torch.dtype) -> Tensor:
        return self.frac64 if dtype == torch.float64 else self.frac32

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size()
                   for t in (self.top_left, self.frac64, self.frac32, self.rows))


def deform_conv2d(x: Tensor, plan: Plan, weight: Tensor, bias: Optional[Tensor],
                  groups: int) -> Tensor:
    """The calibrated convolution of CPU tensors through the native operator.

    # Shapes
    - ``x``: ``[B, C_in, H, W]`` (the plan's input size), any float dtype (float16 / bfloat16
      computed in float32, the output cast back)
    - ``weight``: ``[C_out, C_in / groups, kh, kw]``; ``bias``: ``[C_out]``
    - output: ``[B, C_out, H_out, W_out]``, in the input's memory format
    """
    if not _registered and not available():
        raise RuntimeError(f"calibconv's native operators are not available: {fallback_reason()}")
    ho, wo = plan.output_size
    dtype = x.dtype
    if dtype in (torch.float32, torch.float64) or torch.is_autocast_enabled("cpu"):
        compute = dtype if dtype == torch.float64 else torch.float32
        return torch.ops.calibconv.deform_conv2d(x, weight, bias, plan.top_left,
                                                 plan.frac(compute), plan.rows, ho, wo, groups)
    b = None if bias is None else bias.float()
    out = torch.ops.calibconv.deform_conv2d(x.float(), weight.float(), b, plan.top_left,
                                            plan.frac32, plan.rows, ho, wo, groups)
    return out.to(dtype)


def _memory_format(x: Tensor) -> torch.memory_format:
    """As the kernels' ``memory_format``: channels-last only for a channels-last input that is
    not also NCHW-contiguous."""
    if not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last):
        return torch.channels_last
    return torch.contiguous_format


def _register() -> None:
    lib = "calibconv::deform_conv2d"

    @torch.library.register_fake(lib)
    def _(x, weight, bias, top_left, frac, rows, ho, wo, groups):
        return torch.empty((x.shape[0], weight.shape[0], ho, wo), dtype=x.dtype,
                           device=x.device, memory_format=_memory_format(x))

    @torch.library.register_fake("calibconv::deform_conv2d_backward")
    def _(grad, x, weight, top_left, frac, rows, ho, wo, groups, has_bias, mask):
        def none():
            return x.new_empty((0,))

        gx = torch.empty(x.shape, dtype=x.dtype, device=x.device,
                         memory_format=_memory_format(x)) if mask[0] else none()
        gw = weight.new_empty(weight.shape) if mask[1] else none()
        gb = x.new_empty((weight.shape[0],)) if has_bias and mask[2] else none()
        return gx, gw, gb

    def setup_context(ctx, inputs, output):
        x, weight, bias, top_left, frac, rows, ho, wo, groups = inputs
        ctx.save_for_backward(x, weight, top_left, frac, rows)
        ctx.geometry = (ho, wo, groups)
        ctx.has_bias = bias is not None

    def backward(ctx, grad):
        x, weight, top_left, frac, rows = ctx.saved_tensors
        ho, wo, groups = ctx.geometry
        need = ctx.needs_input_grad
        mask = [bool(need[0]), bool(need[1]), bool(ctx.has_bias and need[2])]
        gx, gw, gb = torch.ops.calibconv.deform_conv2d_backward(
            grad, x, weight, top_left, frac, rows, ho, wo, groups, ctx.has_bias, mask)
        return (gx if mask[0] else None, gw if mask[1] else None, gb if mask[2] else None,
                None, None, None, None, None, None)

    torch.library.register_autograd(lib, backward, setup_context=setup_context)
    torch.library.register_autocast(lib, "cpu", torch.float32)
