"""calibconv: calibrated convolutions for fisheye cameras.

The camera models and the calibrated kernel offsets are the Rust crate ``calibconv-geometry``
(the same code as the ``calibconv`` command line), compiled into ``calibconv._native``:

- :class:`Camera`: ``Camera.load(path)`` reads a camera file (``data/cameras/*.toml``),
  ``Camera.import_(tool, path, ...)`` a calibration of Kalibr, OpenCV, Basalt, COLMAP,
  OCamCalib, ROS camera_calibration or ORB-SLAM3; ``project`` / ``unproject`` work on ``[N, 3]`` / ``[N, 2]`` float64 arrays.
- :func:`offsets`: one layer's offsets, float32 ``[2*kh*kw, H_out, W_out]`` in torchvision's
  layout, bit-identical to ``calibconv offsets``.

:mod:`calibconv.torch` (needs torch and torchvision) builds on them: ``CalibratedConv2d``,
``calibrate(model, camera, input_size)`` and ``export_onnx``.

Conventions: pixels ``[u, v]`` = (column, row) with the top-left pixel centre at ``(0, 0)``;
rays ``[x, y, z]`` with x right, y down, z forward; sizes and layer pairs ``(H, W)`` / ``(y, x)``;
``input_padding`` is ``(p_w, p_h)`` (right, bottom), as the CLI's ``--padding PW,PH``.
"""

from ._native import MODELS, Camera, __version__, offsets

__all__ = ["Camera", "offsets", "MODELS", "__version__"]
