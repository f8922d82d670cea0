"""calibconv.Camera: loading, properties, projections against OpenCV's fisheye module, errors.

Oracle: ``cv2.fisheye.projectPoints`` (opencv-python-headless, pinned in requirements.txt), which
implements the same Kannala-Brandt polynomial `d(theta) = theta (1 + k1 theta^2 + ... + k4
theta^8)` independently. OpenCV's model takes `theta = atan(r / z)`, so it is compared on rays in
front of the camera (theta < 90 deg) only.
"""

import json
import math

import cv2
import numpy as np
import pytest

import calibconv

from conftest import CAMERAS, F195, GOLDEN

#: Both sides evaluate the same float64 polynomial; 1e-6 px is ~1e3 x their round-off at
#: ~500 px and far below any formula error (a wrong coefficient moves pixels by > 1e-3 px).
PX_TOL = 1e-6
#: Unit rays of an inverse solved to convergence (the crate's EPS) agree to better than this.
RAY_TOL = 1e-9

STRONG = """model = "kannala-brandt"
width = 1024
height = 944
fov_deg = 170.0
fx = 310.0
fy = 305.0
cx = 512.3
cy = 470.8
k1 = 0.05
k2 = -0.01
k3 = 0.002
k4 = -0.0003
"""


def kb_params(path):
    """K and D of a Kannala-Brandt camera file, read independently of calibconv."""
    import tomllib

    with open(path, "rb") as f:
        t = tomllib.load(f)
    k = np.array([[t["fx"], 0, t["cx"]], [0, t["fy"], t["cy"]], [0, 0, 1]], dtype=np.float64)
    d = np.array([t["k1"], t["k2"], t["k3"], t["k4"]], dtype=np.float64)
    return k, d


def rays_in_front(n=400, max_theta_deg=85.0, seed=0):
    rng = np.random.default_rng(seed)
    theta = np.radians(rng.uniform(0.0, max_theta_deg, n))
    phi = rng.uniform(-math.pi, math.pi, n)
    depth = rng.uniform(0.5, 20.0, n)[:, None]
    unit = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    return unit * depth


def kb_cameras(tmp_path):
    strong = tmp_path / "strong.toml"
    strong.write_text(STRONG)
    return [F195, CAMERAS / "kb120.toml", strong]


def test_load_properties():
    cam = calibconv.Camera.load(F195)
    assert (cam.width, cam.height, cam.model) == (1080, 960, "kannala-brandt")
    assert cam.fov_deg == pytest.approx(195.0, abs=1e-12)
    assert "kannala-brandt" in calibconv.MODELS


def test_every_shipped_camera_loads_and_round_trips():
    for path in sorted(CAMERAS.glob("*.toml")):
        cam = calibconv.Camera.load(path)
        assert cam.model in calibconv.MODELS, path
        px = np.array([[cam.width / 2 - 0.5, cam.height / 2 - 0.5], [cam.width / 3, cam.height / 4]])
        rays = cam.unproject(px)
        assert np.allclose(np.linalg.norm(rays, axis=1), 1.0, atol=RAY_TOL), path
        assert np.abs(cam.project(rays) - px).max() < PX_TOL, path


def test_project_matches_opencv_fisheye(tmp_path):
    for path in kb_cameras(tmp_path):
        cam = calibconv.Camera.load(path)
        k, d = kb_params(path)
        rays = rays_in_front()
        ref, _ = cv2.fisheye.projectPoints(rays[:, None, :], np.zeros(3), np.zeros(3), k, d)
        got = cam.project(rays)
        assert got.shape == (len(rays), 2) and got.dtype == np.float64
        assert np.abs(got - ref[:, 0, :]).max() < PX_TOL, path


def test_unproject_matches_opencv_fisheye(tmp_path):
    # OpenCV projects calibconv's inverse back onto the pixels it came from.
    for path in kb_cameras(tmp_path):
        cam = calibconv.Camera.load(path)
        k, d = kb_params(path)
        px = cam.project(rays_in_front(seed=1))
        rays = cam.unproject(px)
        assert rays.shape == (len(px), 3)
        assert np.allclose(np.linalg.norm(rays, axis=1), 1.0, atol=RAY_TOL)
        back, _ = cv2.fisheye.projectPoints(rays[:, None, :], np.zeros(3), np.zeros(3), k, d)
        assert np.abs(back[:, 0, :] - px).max() < PX_TOL, path


def test_nan_where_the_model_has_no_answer():
    cam = calibconv.Camera.load(CAMERAS / "pers.toml")
    got = cam.project(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]]))
    assert np.isfinite(got[0]).all() and np.isnan(got[1:]).all()
    # F195's polynomial covers [0, pi]: past it (far outside the image circle) there is no ray.
    f195 = calibconv.Camera.load(F195)
    assert np.isnan(f195.unproject([[540.0 + 5000.0, 480.0]])).all()


def test_accepts_lists_and_float32():
    cam = calibconv.Camera.load(F195)
    a = cam.project([[0.1, 0.2, 1.0]])
    b = cam.project(np.array([[0.1, 0.2, 1.0]], dtype=np.float32))
    assert a.shape == (1, 2) and np.abs(a - b).max() < 1e-4


@pytest.mark.parametrize("bad", [np.zeros((4, 2)), np.zeros(3), np.zeros((2, 3, 1))])
def test_wrong_shaped_rays_raise(bad):
    cam = calibconv.Camera.load(F195)
    with pytest.raises(ValueError, match=r"rays must have shape \[N, 3\], got \[" ):
        cam.project(bad)


def test_wrong_shaped_pixels_raise():
    with pytest.raises(ValueError, match=r"pixels must have shape \[N, 2\], got \[5, 3\]"):
        calibconv.Camera.load(F195).unproject(np.zeros((5, 3)))


def test_missing_camera_file_raises(tmp_path):
    missing = tmp_path / "no-such-camera.toml"
    with pytest.raises(FileNotFoundError, match="no-such-camera.toml"):
        calibconv.Camera.load(missing)


def test_invalid_field_names_file_and_field(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(STRONG.replace("fx = 310.0", "fx = -310.0"))
    with pytest.raises(ValueError, match=r"bad.toml.*`fx`"):
        calibconv.Camera.load(bad)


@pytest.mark.parametrize(
    "tool, name, kwargs",
    [
        ("kalibr", "kalibr_camchain.yaml", {}),
        ("opencv", "opencv_fisheye.yaml", {"fov_deg": 190.0}),
        ("opencv", "opencv_standard.json", {}),
        ("basalt", "basalt_calibration.json", {}),
        ("colmap", "colmap_cameras.txt", {}),
        ("ocamcalib", "ocam_calib_results.txt", {}),
        ("kalibr", "kalibr_omni_fov.yaml", {}),
        ("kalibr", "kalibr_omni_fov.yaml", {"camera": 1}),
        ("basalt", "basalt_radtan8.json", {}),
        ("colmap", "colmap_full_opencv.txt", {"camera": 2}),
        ("opencv", "opencv_rational.xml", {}),
        ("opencv", "opencv_old_sample.yaml", {}),
        ("opencv", "opencv_old_sample.xml", {}),
        ("ros", "ros_ost.yaml", {}),
        ("ros", "ros_ost.txt", {"camera": 1}),
        ("ros", "ros_equidistant_ost.yaml", {}),
        ("orbslam3", "orbslam3_old_pinhole.yaml", {}),
        ("orbslam3", "orbslam3_kb8_stereo.yaml", {"camera": 1}),
    ],
)
def test_import(tool, name, kwargs, tmp_path):
    cam = calibconv.Camera.import_(tool, GOLDEN / "calib" / name, **kwargs)
    assert cam.model in calibconv.MODELS and cam.width > 0 and cam.height > 0
    if "fov_deg" in kwargs:
        assert cam.fov_deg == pytest.approx(kwargs["fov_deg"])
    # What was imported reads back as the same camera through a camera file.
    path = tmp_path / "imported.toml"
    path.write_text(cam.to_toml())
    back = calibconv.Camera.load(path)
    assert (back.model, back.width, back.height, back.fov_deg) == (
        cam.model, cam.width, cam.height, cam.fov_deg)
    px = np.array([[cam.width / 2, cam.height / 2], [cam.width / 4, cam.height / 3]])
    assert np.array_equal(back.unproject(px), cam.unproject(px))


def oracle_cases():
    with open(GOLDEN / "calib_oracle.json") as f:
        return json.load(f)["cases"]


@pytest.mark.parametrize("case", oracle_cases(), ids=lambda c: f"{c['file']}-{c['camera']}")
def test_import_projects_like_the_tool(case):
    """Every tool's camera projects the oracle's rays (OpenCV, or the reference formulas of
    tools/make_calib_fixtures.py) onto their pixels, through the Python API."""
    kwargs = {} if case["camera"] is None else {"camera": case["camera"]}
    cam = calibconv.Camera.import_(case["format"], GOLDEN / "calib" / case["file"], **kwargs)
    assert cam.model == case["model"]
    px = cam.project(np.array(case["rays"]))
    assert np.abs(px - np.array(case["pixels"])).max() <= PX_TOL


def test_import_of_a_folding_camera_leaves_the_fold_outside():
    cam = calibconv.Camera.import_("colmap", GOLDEN / "calib" / "colmap_full_opencv.txt", camera=2)
    rays = cam.unproject(np.array([[0.0, 0.0], [960.0, 540.0]]))
    assert np.isnan(rays[0]).all() and np.isfinite(rays[1]).all()


def test_import_errors():
    with pytest.raises(ValueError, match="unknown format `matlab`"):
        calibconv.Camera.import_("matlab", GOLDEN / "calib" / "kalibr_camchain.yaml")
    with pytest.raises(FileNotFoundError, match="nothing.yaml"):
        calibconv.Camera.import_("kalibr", GOLDEN / "calib" / "nothing.yaml")
