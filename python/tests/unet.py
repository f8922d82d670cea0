"""The milesial-style U-Net of the tests: the project's reference implementation
(tools/reference_unet.py, the one the Rust parity tests compare against, state_dict keys as in
milesial/Pytorch-UNet), with small defaults for these tests (3 channels in, 5 classes out,
bilinear up-sampling, width 8)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))

import reference_unet  # noqa: E402


def UNet(n_channels=3, n_classes=5, bilinear=True, base=8):
    return reference_unet.UNet(n_channels, n_classes, bilinear=bilinear, base=base)
