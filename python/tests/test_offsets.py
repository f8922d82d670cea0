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


def test_zero_offsets_at_the_centre_of_a_pinhole():
    # A perspective camera's calibrated kernel at the principal point is the regular kernel.
    cam = calibconv.Camera.load(CAMERAS / "pers.toml")
    h, w = 33, 33
    off = calibconv.offsets(cam, (h, w), input_padding=(0, 0))
    assert np.abs(off[:, h // 2, w // 2]).max() < 0.05


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
