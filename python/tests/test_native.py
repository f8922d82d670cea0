"""The native CPU kernels as the custom operator ``torch.ops.calibconv.deform_conv2d``: against
torchvision's ``deform_conv2d``, finite differences, ``conv2d``, itself (determinism), and
through torch.compile, autocast and the fallback without a compiler.

The extension must be present: these tests compare it with torchvision, and a missing one would
compare torchvision with itself (``CALIBCONV_ALLOW_NO_NATIVE=1`` skips them where that is meant).
"""

import copy
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
import torchvision
from torch import nn

import calibconv
from calibconv import _native, _ops
from calibconv.torch import CalibratedConv2d, calibrate, native_available

from conftest import F195, ROOT, max_rel
from unet import UNet

#: float64 against torchvision's float64: the same products summed in another order (tiles,
#: chunks, the scatter's bands): measured <= 9e-16 relative; 1e-12 is margin, while a wrong
#: corner or weight is >= 1e-3.
F64_TOL = 1e-12
#: float32 against torchvision's float64 on the same values: float32 round-off of sums of up to
#: thousands of products, measured <= 1.8e-6 (a bias gradient, summed over 7000 pixels); 1e-4 is
#: margin, while a wrong corner or weight is >= 1e-3.
F32_TOL = 1e-4
#: Autocast: a map rounded to bfloat16 (8 bits: 2^-9 relative each) or float16 (2^-12) by the
#: convolution before, then float32 sums; against float32 the largest element differs by 4.3e-3
#: (bfloat16) and 5.0e-4 (float16) of the largest value (measured, worst of autocast and a model
#: converted to the type): the bounds are about 7x that.
AUTOCAST_TOL = {torch.bfloat16: 3e-2, torch.float16: 3e-3}

pytestmark = pytest.mark.skipif(
    os.environ.get("CALIBCONV_ALLOW_NO_NATIVE") == "1" and not native_available(),
    reason="CALIBCONV_ALLOW_NO_NATIVE=1 and no native kernels",
)


def test_native_kernels_are_built():
    assert native_available(), f"native kernels not built: {_ops.fallback_reason()}"
    assert hasattr(torch.ops.calibconv, "deform_conv2d")


def test_embedded_sources_are_the_crates():
    # The wheel embeds src/ops/native: every file build.rs compiles into the crate, its headers,
    # and torch_op.cpp (the operators), and nothing else; byte for byte the checkout's files.
    build_rs = (ROOT / "build.rs").read_text()
    listed = set(re.findall(r'"src/ops/native/([\w.]+)"', build_rs))
    sources = dict(_native.native_sources())
    assert set(sources) == listed | {"torch_op.cpp"}
    for name, text in sources.items():
        assert text == (ROOT / "src" / "ops" / "native" / name).read_text(), name


# (C_in, C_out, (H, W), kernel, stride, padding, dilation, groups, bias, offset spread):
# strides, dilation, groups, paddings from 0 to 2; spreads from within a pixel to far off the
# image (then many samples read zeros or partly outside corners).
CASES = [
    (3, 8, (13, 17), (3, 3), (1, 1), (1, 1), (1, 1), 1, True, 0.7),
    (5, 6, (12, 15), (3, 3), (2, 2), (1, 1), (1, 1), 1, False, 2.5),
    (4, 6, (14, 13), (3, 3), (1, 2), (2, 2), (2, 2), 2, True, 1.5),
    (6, 4, (11, 12), (5, 3), (2, 1), (0, 1), (1, 1), 2, True, 8.0),
    (16, 32, (9, 10), (3, 3), (1, 1), (1, 1), (1, 1), 1, True, 30.0),
    (3, 16, (16, 18), (7, 7), (2, 2), (3, 3), (1, 1), 1, False, 1.0),
]


def case_id(c):
    return (f"{c[0]}to{c[1]}-{c[2][0]}x{c[2][1]}-k{c[3][0]}{c[3][1]}-s{c[4][0]}{c[4][1]}"
            f"-p{c[5][0]}{c[5][1]}-d{c[6][0]}-g{c[7]}-b{int(c[8])}-off{c[9]}")


def make_layer(case, dtype, seed=0):
    cin, cout, size, k, stride, pad, dil, groups, bias, spread = case
    g = torch.Generator().manual_seed(seed)
    conv = nn.Conv2d(cin, cout, k, stride=stride, padding=pad, dilation=dil, groups=groups,
                     bias=bias, dtype=torch.float64)
    with torch.no_grad():
        conv.weight.copy_(torch.randn(conv.weight.shape, generator=g, dtype=torch.float64))
        if bias:
            conv.bias.copy_(torch.randn(conv.bias.shape, generator=g, dtype=torch.float64))
    ho = (size[0] + 2 * pad[0] - dil[0] * (k[0] - 1) - 1) // stride[0] + 1
    wo = (size[1] + 2 * pad[1] - dil[1] * (k[1] - 1) - 1) // stride[1] + 1
    off = (torch.rand(2 * k[0] * k[1], ho, wo, generator=g) - 0.5) * 2 * spread
    layer = CalibratedConv2d.from_conv(conv, off.numpy().astype(np.float32), size)
    return layer.to(dtype)


def forward_backward(fn, x, params, upstream):
    x = x.detach().clone().requires_grad_(True)
    params = [p.detach().clone().requires_grad_(True) for p in params]
    out = fn(x, *params)
    out.backward(upstream)
    return out.detach(), [x.grad] + [p.grad for p in params]


def torchvision_fn(layer):
    off = layer.offsets

    def fn(x, w, *b):
        return torchvision.ops.deform_conv2d(
            x, off.to(x.dtype).expand(x.shape[0], -1, -1, -1), w, b[0] if b else None,
            stride=layer.stride, padding=layer.padding, dilation=layer.dilation)

    return fn


def native_fn(layer):
    def fn(x, w, *b):
        return _ops.deform_conv2d(x, layer._plan, w, b[0] if b else None, layer.groups)

    return fn


def params_of(layer):
    return [layer.weight] + ([layer.bias] if layer.bias is not None else [])


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_matches_torchvision_in_float64(case):
    layer = make_layer(case, torch.float64)
    g = torch.Generator().manual_seed(1)
    x = torch.randn(3, case[0], *case[2], generator=g, dtype=torch.float64)
    with torch.no_grad():
        upstream = torch.randn_like(torchvision_fn(layer)(x, *params_of(layer)))
    ref, ref_grads = forward_backward(torchvision_fn(layer), x, params_of(layer), upstream)
    out, grads = forward_backward(native_fn(layer), x, params_of(layer), upstream)
    assert max_rel(out, ref) < F64_TOL
    for name, a, b in zip(["input", "weight", "bias"], grads, ref_grads):
        assert max_rel(a, b) < F64_TOL, name


# float32 takes other paths than float64: the few-output-channel kernels (8 to 1024 outputs, one
# group), the whole-batch gather of 3-channel first layers (batch >= 4), the BLAS for the rest.
F32_CASES = [
    (3, 16, (40, 44), (3, 3), (1, 1), (1, 1), (1, 1), 1, True, 1.0),  # three channels, batch
    (3, 64, (32, 36), (7, 7), (2, 2), (3, 3), (1, 1), 1, False, 2.0),  # resnet18's conv1
    (32, 64, (20, 22), (3, 3), (1, 1), (1, 1), (1, 1), 1, True, 3.0),  # small kernels
    (16, 24, (15, 17), (3, 3), (2, 2), (1, 1), (1, 1), 4, True, 1.0),  # groups: the BLAS
]


@pytest.mark.parametrize("case", F32_CASES, ids=case_id)
@pytest.mark.parametrize("input_grad", [True, False], ids=["input-grad", "first-layer"])
def test_float32_paths_match_torchvision_in_float64(case, input_grad):
    ref_layer = make_layer(case, torch.float64)
    layer = make_layer(case, torch.float32)
    g = torch.Generator().manual_seed(2)
    x = torch.randn(4, case[0], *case[2], generator=g, dtype=torch.float64)
    with torch.no_grad():
        upstream = torch.randn_like(torchvision_fn(ref_layer)(x, *params_of(ref_layer)))
    ref, ref_grads = forward_backward(torchvision_fn(ref_layer), x, params_of(ref_layer),
                                      upstream)
    # Without an input gradient (a first layer) the kernels take the weight gradient's own path.
    x32 = x.float()
    params = [p.detach().clone().requires_grad_(True) for p in params_of(layer)]
    xin = x32.clone().requires_grad_(input_grad)
    out = native_fn(layer)(xin, *params)
    out.backward(upstream.float())
    assert max_rel(out.detach(), ref) < F32_TOL
    grads = ([xin.grad] if input_grad else [None]) + [p.grad for p in params]
    for name, a, b in zip(["input", "weight", "bias"], grads, ref_grads):
        if a is not None:
            assert max_rel(a, b) < F32_TOL, name


def test_gradcheck():
    case = (4, 6, (7, 8), (3, 3), (2, 1), (1, 1), (1, 2), 2, True, 2.0)
    layer = make_layer(case, torch.float64)
    x = torch.randn(2, 4, 7, 8, dtype=torch.float64, requires_grad=True)
    w = layer.weight.detach().clone().requires_grad_(True)
    b = layer.bias.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(native_fn(layer), (x, w, b))


def test_opcheck():
    # Schema, fake (meta) implementation, autograd registration and torch.compile's dispatch
    # (AOT, dynamic shapes) of the operator, by torch's own checker.
    layer = make_layer(CASES[2], torch.float32)
    p = layer._plan
    x = torch.randn(2, 4, 14, 13, requires_grad=True)
    args = (x, layer.weight.detach().requires_grad_(True), layer.bias.detach(), p.top_left,
            p.frac32, p.rows, *p.output_size, layer.groups)
    torch.library.opcheck(torch.ops.calibconv.deform_conv2d.default, args)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_offsets_equal_conv2d(dtype):
    # stride, dilation, groups, padding: as conv2d to round-off (float64: 1e-12; float32: 1e-5,
    # sums of 72 products).
    conv = nn.Conv2d(8, 6, 3, stride=2, padding=2, dilation=2, groups=2, bias=True, dtype=dtype)
    x = torch.randn(3, 8, 19, 23, dtype=dtype)
    ref = conv(x)
    zeros = np.zeros((18, ref.shape[2], ref.shape[3]), np.float32)
    cal = CalibratedConv2d.from_conv(conv, zeros, (19, 23))
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    up = torch.randn_like(ref)
    out, grads = forward_backward(native_fn(cal), x, params_of(cal), up)
    ref_out, ref_grads = forward_backward(lambda x, w, b: nn.functional.conv2d(
        x, w, b, stride=2, padding=2, dilation=2, groups=2), x, params_of(conv), up)
    assert max_rel(out, ref_out) < tol
    for name, a, b in zip(["input", "weight", "bias"], grads, ref_grads):
        assert max_rel(a, b) < tol, name


def test_two_backward_passes_are_bitwise_equal():
    # No atomics: the same gradients, bit for bit, from two runs (a calibrated U-Net step).
    torch.manual_seed(5)
    model = calibrate(UNet(bilinear=True), F195, (64, 72))
    x, y = torch.randn(4, 3, 64, 72), torch.randint(0, 5, (4, 64, 72))

    def grads():
        model.zero_grad()
        nn.functional.cross_entropy(model(x), y).backward()
        return [p.grad.clone() for p in model.parameters()]

    model.eval()  # (batch-norm statistics fixed)
    first, second = grads(), grads()
    assert all(torch.equal(a, b) for a, b in zip(first, second))


def test_channels_last_input_gives_channels_last_output():
    layer = make_layer(CASES[4], torch.float32)
    x = torch.randn(2, 16, 9, 10)
    out = layer(x.contiguous(memory_format=torch.channels_last))
    assert out.is_contiguous(memory_format=torch.channels_last)
    assert max_rel(out.detach(), layer(x).detach()) < F32_TOL


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16], ids=str)
def test_autocast_computes_in_float32(dtype):
    # Under autocast a standard convolution hands the calibrated layer a half-precision map: the
    # layer computes in float32 (register_autocast) and returns float32.
    torch.manual_seed(8)
    conv = nn.Conv2d(8, 32, 3, padding=1)
    layer = make_layer(F32_CASES[2], torch.float32)
    model = nn.Sequential(conv, layer)
    x = torch.randn(2, 8, 20, 22)
    with torch.no_grad():
        ref = model(x)
        with torch.autocast("cpu", dtype=dtype):
            mid = conv(x)
            out = model(x)
        # A model converted to the half type: computed in float32, returned in its type.
        half = copy.deepcopy(model).to(dtype)(x.to(dtype))
    assert mid.dtype == dtype and out.dtype == torch.float32 and half.dtype == dtype
    assert max_rel(out, ref) < AUTOCAST_TOL[dtype]
    assert max_rel(half.float(), ref) < AUTOCAST_TOL[dtype]


def test_torch_compile_training_step_matches_eager():
    # The operator and its backward are nodes of the compiled graph (fake implementations);
    # aot_eager traces forward and backward as inductor does, without its C++ compile time.
    torch.manual_seed(6)
    model = calibrate(UNet(bilinear=True), F195, (64, 72)).eval()
    x, y = torch.randn(2, 3, 64, 72), torch.randint(0, 5, (2, 64, 72))

    def step(m):
        model.zero_grad()
        loss = nn.functional.cross_entropy(m(x), y)
        loss.backward()
        return loss.detach(), [p.grad.clone() for p in model.parameters()]

    ref_loss, ref_grads = step(model)
    compiled = torch.compile(model, backend="aot_eager", fullgraph=True)
    loss, grads = step(compiled)
    assert abs(loss.item() - ref_loss.item()) <= F32_TOL * abs(ref_loss.item())
    assert all(max_rel(a, b) < F32_TOL for a, b in zip(grads, ref_grads))


def test_torch_compile_inductor_inference():
    torch.manual_seed(7)
    model = calibrate(nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(),
                                    nn.Conv2d(8, 4, 3, stride=2, padding=1)), F195, (32, 36))
    x = torch.randn(2, 3, 32, 36)
    with torch.no_grad():
        ref = model(x)
        out = torch.compile(model, fullgraph=True)(x)
    assert max_rel(out, ref) < F32_TOL


def test_without_a_compiler_falls_back_with_one_warning(tmp_path):
    # A fresh process with no compiler and an empty extension cache: one RuntimeWarning naming
    # the reason and the cost, and torchvision's results.
    script = f"""
import warnings, torch, torchvision
from torch import nn
from calibconv.torch import CalibratedConv2d, native_available
import calibconv
conv = nn.Conv2d(3, 4, 3, padding=1)
off = calibconv.offsets({str(F195)!r}, (20, 24))
layer = CalibratedConv2d.from_conv(conv, off, (20, 24))
x = torch.randn(2, 3, 20, 24)
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    a, b = layer(x), layer(x)
print(len(w), native_available())
print(str(w[0].message))
ref = torchvision.ops.deform_conv2d(x, layer.offsets.expand(2, -1, -1, -1), conv.weight,
                                    conv.bias, padding=1)
print(torch.equal(a, ref))
"""
    env = dict(os.environ, CXX=str(tmp_path / "no-such-compiler"),
               CALIBCONV_EXTENSION_DIR=str(tmp_path / "ext"))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    count, message, same = out.stdout.strip().split("\n")
    assert count == "1 False"
    assert "no C++ compiler" in message and "torchvision" in message and "8-24x" in message
    assert same == "True"
