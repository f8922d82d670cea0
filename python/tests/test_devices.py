"""calibconv.torch on each device this machine has, against a float64 CPU reference.

The cases run in float32 on the CPU everywhere, and in float32 and float64 on CUDA where torch
sees a GPU (``tools/cuda_check.py`` runs this file on one). Each builds the same layer or
network twice, the reference in float64 on the CPU and the case on its device and dtype, and
compares the output and every gradient (input, weights, bias; every parameter of a calibrated
U-Net in training mode) with ``max_rel`` (max |a - b| / max |b| per tensor).

Tolerances: float64 against float64 differs only in summation order (CUDA's deformable
convolution accumulates gradients with atomics): ~1e-15 relative, 1e-10 is margin. float32 runs
carry ~1e-6 of round-off per layer; the largest seen on the CPU is given beside each constant.
"""

import copy

import numpy as np
import pytest
import torch
import torchvision
from torch import nn

import calibconv
from calibconv.torch import CalibratedConv2d, calibrate

from conftest import F195, max_rel
from unet import UNet

DEVICES = [("cpu", torch.float32)]
if torch.cuda.is_available():
    DEVICES += [("cuda", torch.float32), ("cuda", torch.float64)]

#: One calibrated layer, float32: the CPU's float32 run measured 4e-7 (outputs) to 2e-6
#: (weight gradients) against float64.
LAYER_TOL = {torch.float32: 1e-4, torch.float64: 1e-10}
#: The U-Net, float32, outputs and loss: 2e-5 measured on the CPU. Its gradients are compared by
#: norm (|a - b| / |b| per tensor), and loosely: in float32 a ReLU input within round-off of 0 can
#: take the other side (on the CPU, one element of up4's second ReLU, whose input gradient then
#: differs by 4e-2 of its largest value), and that difference reaches every earlier gradient
#: (3.2e-3 at most by norm, 3.5e-3 by max_rel; a standard U-Net of the same weights, where no
#: input sits that close to 0, 5e-6). A wrong tap or a missing gradient is O(1).
UNET_TOL = {torch.float32: 1e-4, torch.float64: 1e-10}
UNET_GRAD_TOL = {torch.float32: 5e-2, torch.float64: 1e-10}
UNET_INPUT = (64, 72)

#: (C_in, C_out, input (H, W), kernel, stride, dilation, groups, bias): F195 offsets, the
#: paddings a "same" convolution would have.
LAYERS = [
    (3, 8, (48, 54), 3, 1, 1, 1, True),
    (8, 16, (33, 37), 3, 2, 1, 1, False),
    (16, 16, (24, 28), 3, 1, 2, 2, True),
    (4, 6, (40, 44), 5, 1, 1, 1, True),
]


def ids(cases):
    return [f"{d}-{str(t).removeprefix('torch.')}" for d, t in cases]


def calibrated_layer(cin, cout, size, k, stride, dil, groups, bias):
    pad = dil * (k - 1) // 2
    conv = nn.Conv2d(cin, cout, k, stride=stride, padding=pad, dilation=dil, groups=groups,
                     bias=bias, dtype=torch.float64)
    off = calibconv.offsets(str(F195), size, kernel=k, stride=stride, padding=pad, dilation=dil)
    return CalibratedConv2d.from_conv(conv, off, size)


def run(module, x, upstream):
    """Output and gradients (input, then every parameter by name) of one forward + backward."""
    module.zero_grad()
    x = x.detach().clone().requires_grad_(True)
    out = module(x)
    out.backward(upstream)
    grads = {"input": x.grad}
    grads.update({n: p.grad for n, p in module.named_parameters()})
    return out.detach(), grads


def layer_id(c):
    return f"{c[0]}to{c[1]}-{c[2][0]}x{c[2][1]}-k{c[3]}s{c[4]}d{c[5]}g{c[6]}"


@pytest.mark.parametrize("device,dtype", DEVICES, ids=ids(DEVICES))
@pytest.mark.parametrize("case", LAYERS, ids=layer_id)
def test_layer_matches_float64_cpu(device, dtype, case):
    torch.manual_seed(1)
    ref = calibrated_layer(*case)
    cin, (h, w) = case[0], case[2]
    x = torch.randn(2, cin, h, w, dtype=torch.float64)
    with torch.no_grad():
        upstream = torch.randn_like(ref(x))
    ref_out, ref_grads = run(ref, x, upstream)

    layer = copy.deepcopy(ref).to(device=device, dtype=dtype)
    # Buffers follow .to(): the offsets too (the forward casts them to the input's dtype anyway).
    assert layer.offsets.device.type == device and layer.offsets.dtype == dtype
    out, grads = run(layer, x.to(device, dtype), upstream.to(device, dtype))
    assert out.device.type == device and out.dtype == dtype
    tol = LAYER_TOL[dtype]
    assert max_rel(out.cpu(), ref_out) < tol
    assert set(grads) == set(ref_grads)
    for name, g in grads.items():
        assert max_rel(g.cpu(), ref_grads[name]) < tol, name


@pytest.mark.parametrize("device,dtype", DEVICES, ids=ids(DEVICES))
def test_calibrated_unet_training_step_matches_float64_cpu(device, dtype):
    torch.manual_seed(2)
    ref = UNet(bilinear=True).double()
    calibrate(ref, F195, UNET_INPUT)
    x = torch.randn(2, 3, *UNET_INPUT, dtype=torch.float64)
    y = torch.randint(0, 5, (2, *UNET_INPUT))

    def step(model, x, y):
        model.zero_grad()
        loss = nn.functional.cross_entropy(model(x), y)
        loss.backward()
        return loss.detach(), {n: p.grad for n, p in model.named_parameters()}

    # The copy is taken before the reference's step: its batch-norm running statistics too.
    model = copy.deepcopy(ref).to(device=device, dtype=dtype)
    ref_loss, ref_grads = step(ref, x, y)
    loss, grads = step(model, x.to(device, dtype), y.to(device))
    offsets = [m.offsets for m in model.modules() if isinstance(m, CalibratedConv2d)]
    assert len(offsets) == 18 and all(o.device.type == device for o in offsets)
    tol, grad_tol = UNET_TOL[dtype], UNET_GRAD_TOL[dtype]
    assert abs(loss.item() - ref_loss.item()) < tol * abs(ref_loss.item())
    assert set(grads) == set(ref_grads)
    for name, g in grads.items():
        assert g is not None, name
        g, r = g.cpu().double(), ref_grads[name]
        err = max_rel(g, r) if dtype == torch.float64 else float((g - r).norm() / r.norm())
        assert err < grad_tol, name
    # The running statistics were updated on the device as on the CPU.
    for (name, b), (_, rb) in zip(model.named_buffers(), ref.named_buffers()):
        if b.is_floating_point() and not name.endswith("offsets"):
            assert max_rel(b.cpu(), rb) < tol, name


@pytest.mark.parametrize("device,dtype", DEVICES, ids=ids(DEVICES))
def test_calibrate_a_model_already_on_the_device(device, dtype):
    # calibrate() runs its sizing forward on the model's device and dtype and puts the offsets
    # there; the state_dict (no offsets in it) moves to and from the CPU unchanged.
    torch.manual_seed(3)
    model = UNet(bilinear=False).to(device=device, dtype=dtype)
    keys = list(model.state_dict())
    calibrate(model, F195, UNET_INPUT)
    cal = [m for m in model.modules() if isinstance(m, CalibratedConv2d)]
    assert len(cal) == 18
    assert all(m.offsets.device.type == device and m.weight.device.type == device for m in cal)
    assert list(model.state_dict()) == keys
    x = torch.randn(1, 3, *UNET_INPUT, device=device, dtype=dtype)
    model.eval()
    with torch.no_grad():
        here = model(x)
        model.cpu()
        assert all(m.offsets.device.type == "cpu" for m in cal)
        there = model(x.cpu())
    assert here.device.type == device and there.device.type == "cpu"
    assert max_rel(here.cpu().double(), there.double()) < LAYER_TOL[dtype] * 10
    assert np.isfinite(there.double().numpy()).all()


@pytest.mark.parametrize("device,dtype", DEVICES, ids=ids(DEVICES))
def test_batch_split_under_the_column_limit_is_the_same_computation(device, dtype, monkeypatch):
    # torchvision's CUDA kernel fails on column buffers of 2.24 * 2^31 elements (see
    # MAX_COLUMN_ELEMENTS): the forward splits the batch. Here the limit is lowered so that a
    # batch of 5 runs as chunks of 2, 2 and 1, against one call.
    import calibconv.torch as ct

    torch.manual_seed(4)
    layer = calibrated_layer(8, 16, (33, 37), 3, 2, 1, 1, True).to(device=device, dtype=dtype)
    x = torch.randn(5, 8, 33, 37, device=device, dtype=dtype)
    upstream = torch.randn(5, 16, 17, 19, device=device, dtype=dtype)
    whole_out, whole = run(layer, x, upstream)
    calls = []
    # (On the CPU the layer runs the native kernels, which have no such limit: the split is
    # torchvision's path, taken here.)
    monkeypatch.setattr(ct._ops, "available", lambda: False)
    monkeypatch.setattr(ct, "deform_conv2d", lambda inp, *a, **k: calls.append(inp.shape[0])
                        or torchvision.ops.deform_conv2d(inp, *a, **k))
    monkeypatch.setattr(ct, "MAX_COLUMN_ELEMENTS", 8 * 9 * 17 * 19 * 2 + 5)
    split_out, split = run(layer, x, upstream)
    assert calls == [2, 2, 1]
    tol = LAYER_TOL[dtype]
    assert max_rel(split_out.cpu().double(), whole_out.cpu().double()) < tol
    for name, g in split.items():
        assert max_rel(g.cpu().double(), whole[name].cpu().double()) < tol, name
