"""export_onnx: calibrated models as ONNX DeformConv (opset 19) with the offsets as constants,
run in onnxruntime's CPU provider against PyTorch."""

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from torch import nn

from calibconv.torch import CalibratedConv2d, calibrate, export_onnx

from conftest import F195, max_rel
from test_torch import UNET_CALIBRATED, UNET_INPUT
from unet import UNet

#: onnxruntime's DeformConv and torchvision's deform_conv2d, both float32, sum the same
#: products in different orders: ~1e-6 of the largest value over a network's depth; the issue's
#: bound 1e-4 is margin, while a wrong offset layout (dx / dy swapped) is an error of ~1e-1.
ONNX_REL_TOL = 1e-4


def run_onnx(path, x):
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return sess.run(None, {sess.get_inputs()[0].name: x.numpy()})[0]


def op_counts(path):
    counts = {}
    for node in onnx.load(str(path)).graph.node:
        counts[node.op_type] = counts.get(node.op_type, 0) + 1
    return counts


def calibrated_unet():
    torch.manual_seed(0)
    model = calibrate(UNet(bilinear=True), F195, UNET_INPUT).eval()
    # Non-trivial batch-norm statistics, so that every layer matters.
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    return model


def test_unet_onnx_parity(tmp_path):
    model = calibrated_unet()
    x = torch.randn(2, 3, *UNET_INPUT)
    path = export_onnx(model, x, tmp_path / "unet.onnx")
    assert op_counts(path).get("DeformConv") == UNET_CALIBRATED
    with torch.no_grad():
        ref = model(x).numpy()
    assert max_rel(run_onnx(path, x), ref) <= ONNX_REL_TOL
    # The offsets are constants of the graph, not inputs.
    assert [i.name for i in onnx.load(str(path)).graph.input] == ["x"]


def test_torchscript_exporter_parity(tmp_path):
    torch.manual_seed(1)
    conv = nn.Conv2d(3, 8, 3, stride=2, padding=1, groups=1)
    model = calibrate(nn.Sequential(conv, nn.ReLU()), F195, (48, 54)).eval()
    assert isinstance(model[0], CalibratedConv2d)
    x = torch.randn(1, 3, 48, 54)
    path = export_onnx(model, x, tmp_path / "one.onnx", dynamo=False)
    assert op_counts(path).get("DeformConv") == 1
    with torch.no_grad():
        ref = model(x).numpy()
    assert max_rel(run_onnx(path, x), ref) <= ONNX_REL_TOL


def test_opset_below_19_raises(tmp_path):
    with pytest.raises(ValueError, match="opset 18: ONNX DeformConv needs opset >= 19"):
        export_onnx(nn.Identity(), torch.zeros(1), tmp_path / "x.onnx", opset=18)
