"""calibconv.torch: CalibratedConv2d and calibrate() on torchvision's resnet18 and a
milesial-style U-Net, on the CPU (test_devices.py repeats the numerical cases on CUDA where
torch sees a GPU)."""

import numpy as np
import pytest
import torch
import torchvision
from safetensors.torch import load_file
from torch import nn

import calibconv
from calibconv.torch import CalibratedConv2d, calibrate

from conftest import F195, GOLDEN, max_rel
from unet import UNet

#: Float32 deform_conv2d against a float64 reference rounded to float32 (the fixture), and
#: float32 runs against each other: sums of <= 8 x 25 products of O(1) values carry round-off
#: ~1e-6 of the largest value; 1e-4 is margin, while a wrong tap or bilinear weight is >= 1e-2.
REL_TOL = 1e-4
#: resnet18 on the F195 aspect: its last stage sees a 4x4 map, the narrowest that a 3x3 kernel
#: can calibrate for a 195 deg lens (3 * 195 / 4 = 146 deg, under the 178 deg limit).
RESNET_INPUT = (112, 128)
UNET_INPUT = (64, 72)
#: The 3x3 and 7x7 convolutions of resnet18 (the 1x1 downsample convolutions stay standard).
RESNET18_CALIBRATED = 17
#: inc, down1..4 and up1..4 hold two 3x3 convolutions each; outc is 1x1.
UNET_CALIBRATED = 18

torch.manual_seed(0)


def conv_names(model, cls=nn.Conv2d):
    return [n for n, m in model.named_modules() if isinstance(m, cls)]


def test_zero_offsets_equal_conv2d():
    conv = nn.Conv2d(4, 6, 3, stride=2, padding=1, dilation=1, groups=2, bias=True)
    x = torch.randn(2, 4, 11, 13)
    ref = conv(x)
    zeros = np.zeros((18, ref.shape[2], ref.shape[3]), np.float32)
    cal = CalibratedConv2d.from_conv(conv, zeros, (11, 13))
    assert cal.weight is conv.weight and cal.bias is conv.bias
    assert max_rel(cal(x).detach(), ref.detach()) < REL_TOL
    assert set(cal.state_dict()) == set(conv.state_dict()) == {"weight", "bias"}


def test_matches_the_deform_conv2d_fixture_of_the_rust_op():
    # tests/golden/deform_conv2d.safetensors is the reference
    # tests/integration/oracle_torchvision.rs holds calibconv::ops::deform_conv2d to (same inputs,
    # same tolerance).
    fx = load_file(GOLDEN / "deform_conv2d.safetensors")
    cases = sorted({k.split(".")[0] for k in fx})
    checked = 0
    for c in cases:
        off = fx[f"{c}.offset"]
        if off.dim() != 3:  # per-item offsets: not a calibrated layer
            continue
        w, x, meta = fx[f"{c}.weight"], fx[f"{c}.input"], fx[f"{c}.meta"].tolist()
        sh, sw, ph, pw, dh, dw, groups, has_bias = meta
        conv = nn.Conv2d(w.shape[1] * groups, w.shape[0], tuple(w.shape[2:]), stride=(sh, sw),
                         padding=(ph, pw), dilation=(dh, dw), groups=groups, bias=bool(has_bias))
        with torch.no_grad():
            conv.weight.copy_(w)
            if has_bias:
                conv.bias.copy_(fx[f"{c}.bias"])
        cal = CalibratedConv2d.from_conv(conv, off, tuple(x.shape[2:]))
        assert max_rel(cal(x).detach(), fx[f"{c}.output"]) < REL_TOL, c
        checked += 1
    assert checked >= 7


def test_input_size_mismatch_raises():
    conv = nn.Conv2d(3, 4, 3, padding=1)
    cal = CalibratedConv2d.from_conv(conv, calibconv.offsets(str(F195), (30, 34)), (30, 34))
    with pytest.raises(ValueError, match=r"input feature map is \(30, 36\).*made for \(30, 34\)"):
        cal(torch.randn(1, 3, 30, 36))
    with pytest.raises(ValueError, match=r"offsets of shape \[18, 30, 34\] do not fit"):
        CalibratedConv2d.from_conv(nn.Conv2d(3, 4, 3, padding=0), np.zeros((18, 30, 34)), (30, 34))


def test_calibrate_resnet18():
    model = torchvision.models.resnet18(num_classes=10).eval()
    keys = list(model.state_dict())
    ptrs = {k: v.data_ptr() for k, v in model.state_dict().items()}
    convs = [n for n, m in model.named_modules() if isinstance(m, nn.Conv2d) and m.kernel_size[0] > 1]
    assert len(convs) == RESNET18_CALIBRATED
    x = torch.randn(2, 3, *RESNET_INPUT)
    before = model(x)
    calibrate(model, F195, RESNET_INPUT)
    assert sorted(conv_names(model, CalibratedConv2d)) == sorted(convs)
    assert list(model.state_dict()) == keys
    assert {k: v.data_ptr() for k, v in model.state_dict().items()} == ptrs  # weights shared
    assert model.conv1.input_size == RESNET_INPUT and model.layer4[1].conv2.input_size == (4, 4)
    out = model(x)
    assert out.shape == before.shape and torch.isfinite(out).all()
    # Calibrated kernels sample elsewhere: the output changes.
    assert max_rel(out.detach(), before.detach()) > 1e-3
    # A checkpoint of the standard model loads strictly into the calibrated one.
    model.load_state_dict(torchvision.models.resnet18(num_classes=10).state_dict(), strict=True)


def test_calibrate_unet_and_fine_tune():
    model = UNet(bilinear=True)
    keys = list(model.state_dict())
    calibrate(model, calibconv.Camera.load(F195), UNET_INPUT)
    assert len(conv_names(model, CalibratedConv2d)) == UNET_CALIBRATED
    assert list(model.state_dict()) == keys
    assert model.down4.maxpool_conv[1].double_conv[0].input_size == (4, 4)
    assert model.training  # calibrate() restores the mode it found
    opt = torch.optim.SGD(model.parameters(), lr=1e-2)
    x, y = torch.randn(2, 3, *UNET_INPUT), torch.randint(0, 5, (2, *UNET_INPUT))
    loss = nn.functional.cross_entropy(model(x), y)
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
    opt.step()


def test_calibrate_unet_transposed():
    model = UNet(bilinear=False)
    calibrate(model, F195, UNET_INPUT, input_padding=(2, 0), convention="paper")
    # ConvTranspose2d (the up-sampling) is not an nn.Conv2d: it stays.
    assert len(conv_names(model, CalibratedConv2d)) == UNET_CALIBRATED
    assert len(conv_names(model, nn.ConvTranspose2d)) == 4
    assert model(torch.randn(1, 3, *UNET_INPUT)).shape == (1, 5, *UNET_INPUT)


def test_feature_map_too_small_names_the_layer():
    # At 64x64, layer4.0.conv1 sees 4x4 (146 deg for F195, fine) and layer4.0.conv2 2x2.
    model = torchvision.models.resnet18(num_classes=10)
    with pytest.raises(ValueError, match=r"layer4\.0\.conv2 \(input feature map 2x2\).*field of view"):
        calibrate(model, F195, (64, 64))


def test_missing_camera_file_raises():
    with pytest.raises(FileNotFoundError, match="missing.toml"):
        calibrate(UNet(), "missing.toml", UNET_INPUT)


def test_even_kernels_stay_standard_with_a_warning():
    model = nn.Sequential(nn.Conv2d(3, 4, 3, padding=1), nn.Conv2d(4, 4, 2, padding=1))
    with pytest.warns(UserWarning, match=r"left standard .*: 1"):
        calibrate(model, F195, (32, 36))
    assert isinstance(model[0], CalibratedConv2d) and type(model[1]) is nn.Conv2d


def test_calibrate_takes_the_input_channels_from_the_first_convolution():
    # A 4-channel input (RGB-D): without in_channels the probe forward reads the first conv's.
    model = nn.Sequential(nn.Conv2d(4, 8, 3, padding=1), nn.ReLU(), nn.Conv2d(8, 2, 3, padding=1))
    calibrate(model, F195, (32, 36))
    assert len(conv_names(model, CalibratedConv2d)) == 2
    assert model(torch.randn(2, 4, 32, 36)).shape == (2, 2, 32, 36)


def test_calibrate_without_a_convolution_asks_for_in_channels():
    with pytest.raises(ValueError, match="pass in_channels"):
        calibrate(nn.Sequential(nn.Linear(4, 4)), F195, (32, 36))
