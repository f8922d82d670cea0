"""calibconv.offsets against the `calibconv offsets` command, bit for bit, and its errors.

Both call the geometry crate's `compute_offsets`; what is tested is the binding: argument
mapping (kernel / stride / dilation / padding pairs, "same" padding, the input padding's
`(p_w, p_h)` order, the convention) and the layout `[2*kh*kw, H_out, W_out]`.
"""

import numpy as np
import pytest
from safetensors.numpy import load_file

import calibconv

from conftest import CAMERAS, F195, run_cli

# (camera, (H, W), kernel, stride, dilation, conv padding or None, input padding (p_w, p_h),
#  convention)
CASES = [
    ("f195.toml", (60, 68), 3, 1, 1, None, (0, 0), "half-pixel"),
    ("f195.toml", (61, 67), 3, 2, 1, None, (2, 0), "paper"),
    ("f195.toml", (48, 54), 5, 1, 2, 3, (0, 0), "half-pixel"),
    ("kb240.toml", (30, 34), 3, 1, 1, 0, (0, 6), "half-pixel"),
    ("ds_example.toml", (32, 40), 7, 2, 1, None, (0, 0), "half-pixel"),
    ("equirect.toml", (16, 32), 3, 1, 1, None, (0, 0), "half-pixel"),
    ("rect-f165.toml", (24, 30), 3, 1, 1, None, (0, 0), "paper"),
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-{c[1][0]}x{c[1][1]}-k{c[2]}")
def test_bit_identical_to_cli(case, cli, tmp_path):
    name, (h, w), k, s, d, p, (pw, ph), conv = case
    out = tmp_path / "off.safetensors"
    args = ["offsets", "--camera", str(CAMERAS / name), "--size", f"{h}x{w}", "--kernel", str(k),
            "--stride", str(s), "--dilation", str(d), "--padding", f"{pw},{ph}",
            "--convention", conv, "--out", str(out)]
    if p is not None:
        args += ["--conv-padding", str(p)]
    run_cli(cli, *args)
    ref = load_file(out)["offsets"]
    cam = calibconv.Camera.load(CAMERAS / name)
    got = calibconv.offsets(cam, size=(h, w), kernel=k, stride=s, padding=p, dilation=d,
                            input_padding=(pw, ph), convention=conv)
    assert got.dtype == np.float32 and got.shape == ref.shape
    # Bit for bit (NaN-free by construction, so byte equality is value equality).
    assert got.tobytes() == ref.tobytes()
    assert np.abs(got).max() > 0.01


def test_layout_and_pairs():
    cam = calibconv.Camera.load(F195)
    off = calibconv.offsets(cam, (40, 44), kernel=(3, 5), stride=(1, 2), dilation=(2, 1))
    # H_out = 40 (same padding 2 on rows), W_out = (44 + 2*2 - 5) // 2 + 1 = 22.
    assert off.shape == (2 * 15, 40, 22)
    # A path works as the camera, and equals the loaded camera's offsets.
    assert np.array_equal(calibconv.offsets(str(F195), (40, 44)), calibconv.offsets(cam, (40, 44)))


#: Float32 storage of offsets below 1 px: 6e-8 px; the float64 formula below agrees far better.
CENTRE_TOL = 1e-6


def test_pinhole_centre_is_the_scaled_regular_kernel():
    # At a pinhole's principal point the calibrated kernel is the regular grid scaled by f / d
    # (the feature map's focal over the virtual kernel's, d = k / (2 tan(k FOV / 2 W))).
    # PERS: f = 540 px, 1080x960, 90 deg; at 32x36 with the `paper` convention the principal
    # point (540, 480) / 30 = (18, 16) is the anchor of output pixel (16, 18).
    cam = calibconv.Camera.load(CAMERAS / "pers.toml")
    off = calibconv.offsets(cam, (32, 36), convention="paper")
    f, d = 540.0 / 30.0, 3.0 / (2.0 * np.tan(np.radians(3 * 90.0 / 36) / 2.0))
    for i in range(3):
        for j in range(3):
            k = i * 3 + j
            expect = ((i - 1) * (f / d - 1.0), (j - 1) * (f / d - 1.0))
            got = off[2 * k : 2 * k + 2, 16, 18]
            assert np.abs(got - expect).max() < CENTRE_TOL, (i, j, got, expect)


def test_feature_map_too_small_for_the_field_of_view():
    cam = calibconv.Camera.load(F195)
    with pytest.raises(ValueError, match=r"3-pixel-wide feature map .*field of view"):
        calibconv.offsets(cam, (3, 3))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"kernel": 4}, r"kernel \[4, 4\]: calibrated kernels need odd sizes"),
        ({"stride": 0}, r"stride must be >= 1"),
        ({"kernel": (3, 3, 3)}, r"kernel must be an int or a pair of ints"),
        ({"convention": "centre"}, r"unknown pixel convention `centre`"),
        ({"size": (0, 10)}, r"size must be >= 1"),
    ],
)
def test_bad_arguments(kwargs, message):
    cam = calibconv.Camera.load(F195)
    kwargs = {"size": (30, 34), **kwargs}
    with pytest.raises(ValueError, match=message):
        calibconv.offsets(cam, **kwargs)


def test_missing_camera_path():
    with pytest.raises(FileNotFoundError, match="nope.toml"):
        calibconv.offsets("nope.toml", (30, 34))
