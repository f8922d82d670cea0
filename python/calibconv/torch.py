"""Calibrated convolutions for any PyTorch CNN (needs torch and torchvision).

- :class:`CalibratedConv2d`: an ``nn.Conv2d`` (same parameters, same ``state_dict`` keys) whose
  forward is a deformable convolution with fixed offsets, the paper's "fisheye calibrated kernel"
  (Section 3.2). On the CPU it runs the Rust crate's native kernels as the custom operator
  ``torch.ops.calibconv.deform_conv2d`` (:mod:`calibconv._ops`; compiled against the installed
  torch at first use, :mod:`calibconv._extension`) through a sampling plan built once per layer;
  on other devices, during ONNX export, and where the kernels cannot be built (one
  ``RuntimeWarning`` says why), ``torchvision.ops.deform_conv2d``. The offsets are a
  non-persistent buffer (not in the ``state_dict``; they follow ``.to(device)``) of shape
  ``[1, 2*kh*kw, H_out, W_out]``, expanded over the batch for torchvision (a view, never a copy).
- :func:`calibrate`: swaps every ``nn.Conv2d`` with a kernel larger than 1x1 in a model for a
  ``CalibratedConv2d`` sharing its weights, with offsets for the feature-map size that layer sees
  (found by one dummy forward with hooks).
- :func:`export_onnx`: ONNX with the offsets as constants and ``DeformConv`` (opset >= 19).

Conventions are those of :func:`calibconv.offsets`: pixel centres at integers (top-left pixel
at ``(0, 0)``), pairs ``(y, x)`` = (rows, columns) for sizes, strides, paddings and dilations,
offsets per tap (row-major) as ``(dy, dx)``, torchvision's layout. ``input_padding`` is
``(p_w, p_h)``, pixels added to the right and bottom of the camera image to form the network
input, as in the CLI's ``--padding PW,PH``.
"""

from __future__ import annotations

import os
import warnings
from typing import Optional, Sequence, Tuple, Union

import numpy as np
import torch
from torch import Tensor, nn
from torchvision.ops import deform_conv2d

from . import _ops

__all__ = [
    "CalibratedConv2d", "calibrate", "export_onnx", "native_available", "MIN_DEFORM_CONV_OPSET",
]

#: ``DeformConv`` entered the ONNX standard domain in opset 19.
MIN_DEFORM_CONV_OPSET = 19

#: Elements of torchvision's column buffer (``C_in * kh * kw`` for every output pixel of every
#: item it processes at once) that one ``deform_conv2d`` call may have. torchvision 0.26's CUDA
#: kernel fails with an illegal memory access in the backward pass above some such size (H200:
#: 64->64 at 960x1088, batch 8, 2.24 * 2^31 elements, fails; batch 4, 1.12 * 2^31, works; the
#: forward works at both): the classic U-Net at the paper's input size and batch. The forward
#: splits the batch into chunks of at most this many elements (whole items; one item always
#: goes alone) and concatenates the outputs, which is the same computation (items are
#: independent; the weight gradient sums over the chunks). ``tools/cuda_check.py`` measures it.
MAX_COLUMN_ELEMENTS = 2**31 - 1


#: Set by :func:`export_onnx` while it exports: calibrated layers then trace torchvision's op,
#: which the exporters translate to ONNX ``DeformConv`` with the offsets as constants (the native
#: operator takes a sampling plan, not offsets).
_EXPORTING = False


def native_available() -> bool:
    """Whether calibrated layers on the CPU run the native kernels (building them on the first
    call, see :mod:`calibconv._extension`); ``False`` means torchvision's ``deform_conv2d``."""
    return _ops.available()


def _pair(v) -> Tuple[int, int]:
    if isinstance(v, (tuple, list)):
        if len(v) != 2:
            raise ValueError(f"expected an int or a pair, got {v!r}")
        return int(v[0]), int(v[1])
    return int(v), int(v)


def _numeric_padding(conv: nn.Conv2d) -> Tuple[int, int]:
    """The conv's zero padding as ``(pad_h, pad_w)``, resolving ``"same"`` / ``"valid"``."""
    if isinstance(conv.padding, str):
        if conv.padding == "valid":
            return 0, 0
        # "same" with stride 1: PyTorch pads d*(k-1) in total, the odd pixel on the right/bottom;
        # for odd kernels (the only ones calibrated) that is d*(k-1)/2 on each side.
        ks, dil = _pair(conv.kernel_size), _pair(conv.dilation)
        return tuple(d * (k - 1) // 2 for k, d in zip(ks, dil))  # type: ignore[return-value]
    return _pair(conv.padding)


class CalibratedConv2d(nn.Conv2d):
    """An ``nn.Conv2d`` whose taps sample at fixed, camera-derived offsets.

    Build one from an existing convolution with :meth:`from_conv` (weights shared) or like an
    ``nn.Conv2d`` followed by :meth:`set_offsets`. Without offsets it refuses to run.

    # Shapes
    - input: ``[N, C_in, H, W]`` with ``(H, W)`` equal to :attr:`input_size`;
    - offsets buffer: ``[1, 2*kh*kw, H_out, W_out]`` float32;
    - output: ``[N, C_out, H_out, W_out]`` (PyTorch's conv output size).
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if self.padding_mode != "zeros":
            raise ValueError(
                f"CalibratedConv2d supports padding_mode='zeros' only (deform_conv2d pads with "
                f"zeros), got padding_mode={self.padding_mode!r}"
            )
        self.register_buffer("offsets", None, persistent=False)
        #: ``(H, W)`` of the input feature map the offsets were made for.
        self.input_size: Optional[Tuple[int, int]] = None
        #: The sampling plan of the native kernels (CPU tensors, not a buffer: it stays on the
        #: CPU whatever ``.to()`` does), built by :meth:`set_offsets`.
        self._plan: Optional[_ops.Plan] = None

    @classmethod
    def from_conv(cls, conv: nn.Conv2d, offsets, input_size: Sequence[int]) -> "CalibratedConv2d":
        """A calibrated copy of ``conv`` sharing its ``weight`` and ``bias`` Parameters.

        ``offsets``: ``[2*kh*kw, H_out, W_out]`` or ``[1, 2*kh*kw, H_out, W_out]`` (numpy or
        tensor) for an input feature map of ``input_size = (H, W)``.
        """
        # Built on the meta device (no allocation), then given the original Parameters.
        new = cls(
            conv.in_channels,
            conv.out_channels,
            conv.kernel_size,
            stride=conv.stride,
            padding=conv.padding,
            dilation=conv.dilation,
            groups=conv.groups,
            bias=conv.bias is not None,
            padding_mode=conv.padding_mode,
            device="meta",
            dtype=conv.weight.dtype,
        )
        new.weight = conv.weight
        new.bias = conv.bias
        new.train(conv.training)
        new.set_offsets(offsets, input_size)
        return new

    def set_offsets(self, offsets, input_size: Sequence[int]) -> None:
        """Sets the offsets (see :meth:`from_conv`), on the device of the weights."""
        off = torch.as_tensor(np.asarray(offsets) if not isinstance(offsets, Tensor) else offsets)
        given = list(off.shape)
        if off.dim() == 3:
            off = off.unsqueeze(0)
        h, w = (int(s) for s in input_size)
        kh, kw = self.kernel_size
        ph, pw = _numeric_padding(self)
        sh, sw = self.stride
        dh, dw = self.dilation
        ho = (h + 2 * ph - dh * (kh - 1) - 1) // sh + 1
        wo = (w + 2 * pw - dw * (kw - 1) - 1) // sw + 1
        want = (1, 2 * kh * kw, ho, wo)
        if tuple(off.shape) != want:
            raise ValueError(
                f"offsets of shape {given} do not fit a {kh}x{kw} kernel (stride "
                f"{self.stride}, padding {(ph, pw)}, dilation {self.dilation}) on a {h}x{w} input: "
                f"expected {list(want[1:])} or {list(want)}"
            )
        device = self.weight.device if self.weight.device.type != "meta" else "cpu"
        self.offsets = off.to(device=device, dtype=torch.float32).contiguous()
        self.input_size = (h, w)
        self._plan = _ops.Plan(self.offsets[0].cpu().numpy(), (h, w), self.kernel_size,
                               self.stride, (ph, pw), self.dilation)

    def forward(self, x: Tensor) -> Tensor:
        if self.offsets is None:
            raise RuntimeError("CalibratedConv2d has no offsets: call set_offsets() first")
        if tuple(x.shape[-2:]) != self.input_size:
            raise ValueError(
                f"CalibratedConv2d: input feature map is {tuple(x.shape[-2:])} (H, W), but the "
                f"offsets were made for {self.input_size}: calibrate the model for this input size"
            )
        if x.device.type == "cpu" and not _EXPORTING and not torch.onnx.is_in_onnx_export():
            if _ops.available():
                return _ops.deform_conv2d(x, self._plan, self.weight, self.bias, self.groups)
            _ops.warn_fallback()
        return self._torchvision_forward(x)

    def _torchvision_forward(self, x: Tensor) -> Tensor:
        """``torchvision.ops.deform_conv2d`` with the offsets expanded over the batch, in chunks
        of at most ``MAX_COLUMN_ELEMENTS`` column elements."""
        off = self.offsets if self.offsets.dtype == x.dtype else self.offsets.to(x.dtype)
        kh, kw = self.kernel_size
        per_item = self.in_channels * kh * kw * off.shape[2] * off.shape[3]
        chunk = max(1, MAX_COLUMN_ELEMENTS // per_item)
        pieces = [
            deform_conv2d(
                part,
                off.expand(part.shape[0], -1, -1, -1),
                self.weight,
                self.bias,
                stride=self.stride,
                padding=_numeric_padding(self),
                dilation=self.dilation,
            )
            for part in (x.split(chunk) if x.shape[0] > chunk else (x,))
        ]
        return pieces[0] if len(pieces) == 1 else torch.cat(pieces)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", input_size={self.input_size}"


def _is_calibratable(conv: nn.Module) -> bool:
    return (
        isinstance(conv, nn.Conv2d)
        and not isinstance(conv, CalibratedConv2d)
        and max(conv.kernel_size) > 1
    )


def calibrate(
    model: nn.Module,
    camera,
    input_size: Sequence[int],
    input_padding: Sequence[int] = (0, 0),
    convention: str = "half-pixel",
    in_channels: Optional[int] = None,
) -> nn.Module:
    """Replaces every ``nn.Conv2d`` with a kernel > 1 by a :class:`CalibratedConv2d`.

    ``camera``: a :class:`calibconv.Camera` or the path of a camera file. ``input_size``: the
    network input ``(H, W)`` (the camera image plus ``input_padding = (p_w, p_h)``, resized to
    it). One forward of a ``[1, in_channels, H, W]`` zero tensor (in eval mode, without
    gradients; ``in_channels`` defaults to the input channels of the model's first ``nn.Conv2d``
    in module order, and is an error naming the model when it has none) records the input feature-map size of each convolution; each is swapped in place
    for a calibrated one with its own stride / padding / dilation / groups, sharing the weight and
    bias Parameters, so ``state_dict`` keys and optimiser state stay valid (fine-tuning works).
    Returns ``model``.

    Convolutions with an even kernel side or a non-zero ``padding_mode`` stay standard (a
    ``UserWarning`` names them). A convolution called at two different sizes, or a feature map too
    small for the field of view, raises ``ValueError`` naming the layer.
    """
    from . import Camera, offsets as compute

    if isinstance(camera, (str, os.PathLike)):
        camera = Camera.load(camera)
    h, w = (int(s) for s in input_size)
    if in_channels is None:
        first = next((m for m in model.modules() if isinstance(m, nn.Conv2d)), None)
        if first is None:
            raise ValueError(
                f"{type(model).__name__} has no nn.Conv2d to take the input channels from: "
                f"pass in_channels"
            )
        in_channels = first.in_channels

    sizes: dict = {}
    hooks = []
    names = {m: n for n, m in model.named_modules()}
    for module in model.modules():
        if _is_calibratable(module):

            def hook(mod, inputs, _sizes=sizes):
                size = tuple(int(s) for s in inputs[0].shape[-2:])
                seen = _sizes.setdefault(mod, size)
                if seen != size:
                    raise ValueError(
                        f"{names[mod]}: called on feature maps of {seen} and {size}; one "
                        f"calibrated layer serves one size"
                    )

            hooks.append(module.register_forward_pre_hook(hook))
    try:
        param = next(model.parameters(), None)
        device = param.device if param is not None else torch.device("cpu")
        dtype = param.dtype if param is not None and param.is_floating_point() else torch.float32
        was_training = model.training
        model.eval()
        try:
            with torch.no_grad():
                model(torch.zeros(1, in_channels, h, w, device=device, dtype=dtype))
        finally:
            model.train(was_training)
    finally:
        for hk in hooks:
            hk.remove()

    skipped = []
    for module, size in sizes.items():
        name = names[module]
        if any(k % 2 == 0 for k in module.kernel_size) or module.padding_mode != "zeros":
            skipped.append(name)
            continue
        try:
            off = compute(
                camera,
                size=size,
                kernel=tuple(module.kernel_size),
                stride=tuple(module.stride),
                padding=_numeric_padding(module),
                dilation=tuple(module.dilation),
                input_padding=tuple(input_padding),
                convention=convention,
            )
        except ValueError as e:
            raise ValueError(f"{name} (input feature map {size[0]}x{size[1]}): {e}") from e
        _set_submodule(model, name, CalibratedConv2d.from_conv(module, off, size))
    if skipped:
        warnings.warn(
            "calibrate: left standard (even kernel side or non-zero padding_mode): "
            + ", ".join(skipped)
        )
    return model


def _set_submodule(model: nn.Module, name: str, new: nn.Module) -> None:
    parent_name, _, child = name.rpartition(".")
    parent = model.get_submodule(parent_name) if parent_name else model
    setattr(parent, child, new)


def _deform_conv2d_symbolic(g, input, weight, offset, mask, bias, stride_h, stride_w, pad_h,
                            pad_w, dil_h, dil_w, groups, offset_groups, use_mask):
    """TorchScript-exporter symbolic: ``torchvision::deform_conv2d`` as ONNX ``DeformConv``."""
    from torch.onnx import symbolic_helper as sh

    def i(v):
        return sh._get_const(v, "i", "deform_conv2d attribute")

    if sh._get_const(use_mask, "b", "use_mask"):
        raise NotImplementedError("modulated deform_conv2d (a mask) is not exported; calibconv "
                                  "layers have none")
    inputs = [input, weight, offset]
    if not sh._is_none(bias):
        inputs.append(bias)
    return g.op(
        "DeformConv",
        *inputs,
        strides_i=[i(stride_h), i(stride_w)],
        pads_i=[i(pad_h), i(pad_w), i(pad_h), i(pad_w)],
        dilations_i=[i(dil_h), i(dil_w)],
        group_i=i(groups),
        offset_group_i=i(offset_groups),
    )


def export_onnx(
    model: nn.Module,
    example_input: Tensor,
    path: Union[str, os.PathLike],
    opset: int = MIN_DEFORM_CONV_OPSET,
    dynamo: bool = True,
) -> str:
    """Writes ``model`` (in eval mode) as ONNX to ``path``; returns the path.

    Calibrated layers become ``DeformConv`` nodes with their offsets as constants (initializers);
    the input shape is that of ``example_input`` (calibrated layers serve one size). ``dynamo``
    picks the exporter: ``torch.export`` (default; ``torchvision::deform_conv2d`` is translated by
    onnxscript's torch_lib) or the TorchScript one (a symbolic registered here). While it exports,
    calibrated layers trace torchvision's op, not the native one (whose inputs are a sampling
    plan, which ONNX ``DeformConv`` cannot take). Weights are stored inside the one file.
    """
    if opset < MIN_DEFORM_CONV_OPSET:
        raise ValueError(
            f"opset {opset}: ONNX DeformConv needs opset >= {MIN_DEFORM_CONV_OPSET}"
        )
    global _EXPORTING
    path = os.fspath(path)
    was_training = model.training
    model.eval()
    _EXPORTING = True
    try:
        if dynamo:
            torch.onnx.export(
                model, (example_input,), path, opset_version=opset, dynamo=True,
                external_data=False,
            )
        else:
            torch.onnx.register_custom_op_symbolic(
                "torchvision::deform_conv2d", _deform_conv2d_symbolic, opset
            )
            torch.onnx.export(model, (example_input,), path, opset_version=opset, dynamo=False)
    finally:
        _EXPORTING = False
        model.train(was_training)
    return path
