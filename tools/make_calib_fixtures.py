#!/usr/bin/env python3
"""Calibration files of other tools, and what their cameras project to, for the import tests.

Usage (from the crate root):

    .venv/bin/python tools/make_calib_fixtures.py tests/golden

Writes, deterministically (fixed seeds), into ``tests/golden/calib/``: calibration files in the
formats ``calibconv camera import`` reads, each spelt as its tool writes it (Kalibr camchain,
Basalt JSON, COLMAP cameras.txt, OpenCV FileStorage YAML and XML in the calibration sample's
newer and older spellings, ROS ost.yaml and ost.txt, ORB-SLAM3 settings in both key spellings);
the camera values are made up for these tests. And ``tests/golden/calib_oracle.json``: for each
camera, rays and the pixels the tool's own model gives them (read by
``tests/integration/camera_import.rs``).

Oracles, independent of the Rust code:

- radial-tangential (5 and 8 coefficients): ``cv2.projectPoints``; Kannala-Brandt:
  ``cv2.fisheye.projectPoints`` (OpenCV from the venv), each double-checked here against the
  formula evaluated in NumPy;
- Mei's unified model with radtan (Kalibr ``omni-radtan``) and the FOV model (Kalibr
  ``pinhole-fov``, Basalt ``fov``, COLMAP ``FOV``): written below from the tools' documented
  definitions (Kalibr's ``OmniProjection`` / ``RadialTangentialDistortion`` / ``FovDistortion``;
  Mei and Rives 2007; Devernay and Faugeras 2001, Eq. 13), in NumPy.

Rays are drawn where the source model is defined: in front of the camera for the pinhole models,
within 95 % of the radius at which a distortion folds (its radius stops increasing), within
Basalt's ``rpmax``, and within Mei's projection domain ``z > -w |p|``.
"""

import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np

N_RAYS = 120
#: Agreement of OpenCV with the NumPy formulas: both float64; 1e-9 px is round-off margin.
CHECK_TOL_PX = 1e-9


def rays(rng, theta_max_deg, n=N_RAYS, ok=None):
    """`n` rays `[x, y, z]`, angle to the axis uniform in [0, theta_max], the first on the axis,
    random azimuth and length; `ok(ray)` filters."""
    out = [[0.0, 0.0, 1.7]]
    while len(out) < n:
        t = math.radians(rng.uniform(0.0, theta_max_deg))
        phi = rng.uniform(-math.pi, math.pi)
        length = rng.uniform(0.05, 20.0)
        ray = [length * math.sin(t) * math.cos(phi), length * math.sin(t) * math.sin(phi),
               length * math.cos(t)]
        if ok is None or ok(ray):
            out.append(ray)
    return np.array(out, dtype=np.float64)


def radtan_np(m, k, p):
    """OpenCV's distortion of normalised points `m` [N, 2]; `k` = k1..k6, `p` = p1, p2."""
    x, y = m[:, 0], m[:, 1]
    s = x * x + y * y
    num = 1 + k[0] * s + k[1] * s**2 + k[2] * s**3
    den = 1 + k[3] * s + k[4] * s**2 + k[5] * s**3
    r = num / den
    return np.stack([x * r + 2 * p[0] * x * y + p[1] * (s + 2 * x * x),
                     y * r + p[0] * (s + 2 * y * y) + 2 * p[1] * x * y], 1)


def radial_fold(k):
    """The first undistorted radius where r R(r^2) stops increasing or its denominator reaches 0
    (inf if none below r = 1e3): a dense scan, refined by bisection."""
    def ok(r):
        s = r * r
        num = 1 + k[0] * s + k[1] * s**2 + k[2] * s**3
        den = 1 + k[3] * s + k[4] * s**2 + k[5] * s**3
        h = 1e-7
        f = lambda rr: rr * (1 + k[0] * rr**2 + k[1] * rr**4 + k[2] * rr**6) / (
            1 + k[3] * rr**2 + k[4] * rr**4 + k[5] * rr**6)
        return den > 0 and num / den > 0 and (f(r + h) - f(r - h)) > 0
    prev = 0.0
    for r in np.geomspace(1e-3, 1e3, 20000):
        if not ok(r):
            lo, hi = prev, r
            for _ in range(80):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if ok(mid) else (lo, mid)
            return lo
        prev = r
    return math.inf


def folds_inside(cam):
    """Whether a distortion folds inside the image, judged radially (the tangential terms of
    these cameras move the fold by far less than the margins): an image corner lies farther from
    the principal point than the image of the fold."""
    r = radial_fold(cam["k"])
    if not math.isfinite(r):
        return False
    k = cam["k"]
    s = r * r
    edge = r * (1 + k[0] * s + k[1] * s**2 + k[2] * s**3) / (1 + k[3] * s + k[4] * s**2 + k[5] * s**3)
    fx, fy, cx, cy = cam["f"]
    w, h = cam["size"]
    return any(math.hypot((u - cx) / fx, (v - cy) / fy) > edge
               for u in (-0.5, w - 0.5) for v in (-0.5, h - 0.5))


def opencv_radtan(cam, pts):
    """cv2.projectPoints, double-checked against radtan_np."""
    fx, fy, cx, cy = cam["f"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    k, p = cam["k"], cam["p"]
    D = np.array([k[0], k[1], p[0], p[1], k[2], k[3], k[4], k[5]], dtype=np.float64)
    if not any(k[3:]):
        D = D[:5]
    px, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    px = px.reshape(-1, 2)
    md = radtan_np(pts[:, :2] / pts[:, 2:], k, p)
    ref = np.stack([fx * md[:, 0] + cx, fy * md[:, 1] + cy], 1)
    assert np.abs(px - ref).max() < CHECK_TOL_PX, np.abs(px - ref).max()
    return px


def opencv_fisheye(cam, pts):
    """cv2.fisheye.projectPoints, double-checked against the Kannala-Brandt polynomial."""
    fx, fy, cx, cy = cam["f"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    D = np.array(cam["k"], dtype=np.float64)
    px, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    px = px.reshape(-1, 2)
    q = np.hypot(pts[:, 0], pts[:, 1])
    t = np.arctan2(q, pts[:, 2])
    d = t * (1 + sum(c * t ** (2 * i + 2) for i, c in enumerate(cam["k"])))
    scale = np.where(q > 0, d / np.where(q > 0, q, 1), 0.0)
    ref = np.stack([fx * scale * pts[:, 0] + cx, fy * scale * pts[:, 1] + cy], 1)
    assert np.abs(px - ref).max() < CHECK_TOL_PX, np.abs(px - ref).max()
    return px


def mei_reference(cam, pts):
    """Kalibr's omni-radtan (Mei 2007): m = [x, y] / (z + xi |p|), Kalibr's radtan
    (k1, k2, p1, p2: mx += mx rad + 2 p1 mx my + p2 (r2 + 2 mx^2), my += my rad + 2 p2 mx my +
    p1 (r2 + 2 my^2)), u = fu mx + cu."""
    xi = cam["xi"]
    fu, fv, cu, cv = cam["f"]
    k1, k2 = cam["k"]
    p1, p2 = cam["p"]
    out = []
    for x, y, z in pts:
        d = math.sqrt(x * x + y * y + z * z)
        w = xi if xi <= 1 else 1 / xi
        assert z > -w * d
        mx, my = x / (z + xi * d), y / (z + xi * d)
        r2 = mx * mx + my * my
        rad = k1 * r2 + k2 * r2 * r2
        mxd = mx + mx * rad + 2 * p1 * mx * my + p2 * (r2 + 2 * mx * mx)
        myd = my + my * rad + 2 * p2 * mx * my + p1 * (r2 + 2 * my * my)
        out.append([fu * mxd + cu, fv * myd + cv])
    return np.array(out)


def fov_reference(cam, pts):
    """Devernay and Faugeras Eq. 13 as Kalibr's FovDistortion applies it to x/z, y/z (z > 0):
    r_d = atan(2 r_u tan(w / 2)) / w, m_d = m r_d / r_u."""
    fx, fy, cx, cy = cam["f"]
    w = cam["w"]
    out = []
    for x, y, z in pts:
        assert z > 0
        mx, my = x / z, y / z
        ru = math.hypot(mx, my)
        factor = math.atan(2 * ru * math.tan(w / 2)) / (w * ru) if ru > 0 else 2 * math.tan(w / 2) / w
        out.append([fx * mx * factor + cx, fy * my * factor + cy])
    return np.array(out)


def pinhole_rays(rng, cam, theta_max_deg, bound=math.inf):
    """Rays in front whose x/z radius stays within 95 % of the fold (and `bound`)."""
    limit = 0.95 * min(radial_fold(cam["k"]), bound)
    return rays(rng, theta_max_deg, ok=lambda r: r[2] > 0 and math.hypot(r[0], r[1]) / r[2] < limit)


# ----------------------------------------------------------------------------------------------
# The cameras (made up; `f` = [fx, fy, cx, cy] in the top-left-pixel-centre-at-0 convention)
# ----------------------------------------------------------------------------------------------

OMNI = dict(xi=1.72, f=[757.3, 756.8, 424.1, 401.7], k=[-0.05, 0.13], p=[0.0006, -0.0004],
            size=[848, 800])
KALIBR_FOV = dict(f=[275.6, 275.2, 315.4, 241.8], w=0.9215, size=[640, 480])
RADTAN8 = dict(f=[504.3, 504.4, 323.2, 332.5],
               k=[5.45, 3.55, 0.18, 5.78, 5.39, 0.95], p=[-9e-05, 5e-05], rpmax=1.7,
               size=[640, 576])
BASALT_FOV = dict(f=[260.1, 259.9, 318.7, 243.2], w=0.95, size=[640, 480])
FULL_OPENCV = dict(f=[1450.2, 1449.7, 960.0, 540.0], k=[0.12, -0.3, 0.1, 0.05, -0.02, 0.01],
                   p=[0.0004, -0.0002], size=[1920, 1080])
# Folds inside the image: 1 - 1.35 s + 0.25 s^2 = 0 at r = 0.941, radius 602 px < 960 px.
FOLDING = dict(f=[1000.0, 1000.0, 960.0, 540.0], k=[-0.45, 0.05, 0.0, 0.0, 0.0, 0.0],
               p=[0.0, 0.0], size=[1920, 1080])
COLMAP_FOV = dict(f=[280.1, 279.8, 319.7, 239.8], w=0.93, size=[640, 480])
CV_RATIONAL = dict(f=[612.4, 611.9, 330.2, 238.6],
                   k=[-0.41, 0.22, -0.05, -0.12, 0.08, 0.01], p=[0.0011, -0.0007],
                   size=[640, 480])
CV_OLD = dict(f=[657.46697944293521, 657.46697944293521, 319.5, 239.5],
              k=[-0.41802327176423804, 0.50715244063187526, -0.57843597214487474, 0, 0, 0],
              p=[0.0, 0.0], size=[640, 480])
ROS_PLUMB = dict(f=[454.263963, 453.846471, 366.304669, 241.917291],
                 k=[-0.282519, 0.068547, 0.0, 0, 0, 0], p=[0.000196, 0.00015], size=[752, 480])
ROS_RATIONAL = dict(f=[520.1, 519.6, 321.9, 243.4], k=[2.1, 0.9, 0.02, 2.4, 1.5, 0.17],
                    p=[0.0003, -0.0002], size=[640, 480])
ROS_EQUI = dict(f=[285.7, 285.9, 418.2, 402.6], k=[-0.0063, 0.0418, -0.0396, 0.0065],
                size=[848, 800])
ROS_LEFT = dict(f=[454.26, 453.85, 366.30, 241.92], k=[-0.2825, 0.0685, 0.0112, 0, 0, 0],
                p=[0.0002, 0.00015], size=[752, 480])
ROS_RIGHT = dict(f=[457.59, 456.13, 379.99, 255.24], k=[-0.2836, 0.0731, 0.0, 0, 0, 0],
                 p=[-0.0001, -0.00008], size=[752, 480])
ORB_PINHOLE = dict(f=[458.654, 457.296, 367.215, 248.375],
                   k=[-0.28340811, 0.07395907, 0.0, 0, 0, 0], p=[0.00019359, 1.76187114e-05],
                   size=[752, 480])
ORB_KB1 = dict(f=[190.978477, 190.973307, 254.931706, 256.897442],
               k=[0.0034823894, 0.0007150348, -0.0020532361, 0.0002029367], size=[512, 512])
ORB_KB2 = dict(f=[190.442369, 190.434387, 252.597253, 254.917230],
               k=[0.0034003170, 0.0017669474, -0.0026630898, 0.0003370331], size=[512, 512])


def g(v):
    """A float as the tools print it: repr (round-trips)."""
    return repr(float(v))


def opencv_e3(v):
    """OpenCV 2.x's FileStorage float spelling: 17 significant digits, 3-digit exponent."""
    s = "%.16e" % v
    mant, exp = s.split("e")
    return "%se%s%03d" % (mant, exp[0], abs(int(exp)))


def opencv_xml_scalars(pairs):
    """``(tag, value)`` pairs as OpenCV FileStorage XML elements, one a line."""
    return "\n".join(f"<{tag}>{value}</{tag}>" for tag, value in pairs)


def opencv_xml_matrix(tag, values, rows, fmt):
    """``values`` (row-major) as an OpenCV FileStorage XML matrix ``<tag>`` of ``rows`` rows,
    each value spelt by ``fmt``, the first four on one line and the rest on the next."""
    return f"""<{tag} type_id="opencv-matrix">
  <rows>{rows}</rows>
  <cols>{len(values) // rows}</cols>
  <dt>d</dt>
  <data>
    {' '.join(fmt(v) for v in values[:4])}
    {' '.join(fmt(v) for v in values[4:])}</data></{tag}>"""


def write_files(calib: Path):
    files = {}

    c0, c1 = OMNI, KALIBR_FOV
    files["kalibr_omni_fov.yaml"] = f"""cam0:
  cam_overlaps: []
  camera_model: omni
  distortion_coeffs: [{', '.join(g(v) for v in c0['k'] + c0['p'])}]
  distortion_model: radtan
  intrinsics: [{', '.join(g(v) for v in [c0['xi']] + c0['f'])}]
  resolution: [{c0['size'][0]}, {c0['size'][1]}]
  rostopic: /cam0/image_raw
cam1:
  T_cn_cnm1:
  - [0.9999, 0.0, 0.0141, -0.064]
  - [0.0, 1.0, 0.0, 0.0]
  - [-0.0141, 0.0, 0.9999, 0.0]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: []
  camera_model: pinhole
  distortion_coeffs: [{g(c1['w'])}]
  distortion_model: fov
  intrinsics: [{', '.join(g(v) for v in c1['f'])}]
  resolution: [{c1['size'][0]}, {c1['size'][1]}]
  rostopic: /cam1/image_raw
"""

    r8, bf = RADTAN8, BASALT_FOV
    names8 = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "rpmax"]
    vals8 = r8["f"] + r8["k"][:2] + r8["p"] + r8["k"][2:] + [r8["rpmax"]]
    intr8 = ",\n".join(f'                    "{n}": {g(v)}' for n, v in zip(names8, vals8))
    intrf = ",\n".join(f'                    "{n}": {g(v)}'
                       for n, v in zip(["fx", "fy", "cx", "cy", "w"], bf["f"] + [bf["w"]]))
    files["basalt_radtan8.json"] = f"""{{
    "value0": {{
        "T_imu_cam": [],
        "intrinsics": [
            {{
                "camera_type": "pinhole-radtan8",
                "intrinsics": {{
{intr8}
                }}
            }},
            {{
                "camera_type": "fov",
                "intrinsics": {{
{intrf}
                }}
            }}
        ],
        "resolution": [
            [{r8['size'][0]}, {r8['size'][1]}],
            [{bf['size'][0]}, {bf['size'][1]}]
        ],
        "calib_accel_bias": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        "calib_gyro_bias": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        "imu_update_rate": 200.0,
        "vignette": []
    }}
}}
"""

    def colmap_opencv(cam):
        fx, fy, cx, cy = cam["f"]
        k, p = cam["k"], cam["p"]
        vals = [fx, fy, cx + 0.5, cy + 0.5, k[0], k[1], p[0], p[1], k[2], k[3], k[4], k[5]]
        return " ".join(g(v) for v in vals)

    cf = COLMAP_FOV
    fov_params = " ".join(g(v) for v in [cf["f"][0], cf["f"][1], cf["f"][2] + 0.5,
                                         cf["f"][3] + 0.5, cf["w"]])
    files["colmap_full_opencv.txt"] = f"""# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 3
1 FULL_OPENCV 1920 1080 {colmap_opencv(FULL_OPENCV)}
2 FULL_OPENCV 1920 1080 {colmap_opencv(FOLDING)}
3 FOV 640 480 {fov_params}
"""

    cr = CV_RATIONAL
    K = [cr["f"][0], 0, cr["f"][2], 0, cr["f"][1], cr["f"][3], 0, 0, 1]
    D8 = cr["k"][:2] + cr["p"] + cr["k"][2:]
    files["opencv_rational.xml"] = f"""<?xml version="1.0"?>
<opencv_storage>
{opencv_xml_scalars([
    ("calibration_time", '"Sat Dec  5 10:11:12 2026"'),
    ("nr_of_frames", 24),
    ("image_width", cr['size'][0]),
    ("image_height", cr['size'][1]),
    ("board_width", 9),
    ("board_height", 6),
    ("square_size", "25."),
    ("flags", 16384),
    ("fisheye_model", 0),
])}
{opencv_xml_matrix("camera_matrix", K, 3, g)}
{opencv_xml_matrix("distortion_coefficients", D8, 8, g)}
<avg_reprojection_error>0.2114</avg_reprojection_error>
</opencv_storage>
"""

    co = CV_OLD
    Ko = [co["f"][0], 0.0, co["f"][2], 0.0, co["f"][1], co["f"][3], 0.0, 0.0, 1.0]
    Do = [co["k"][0], co["k"][1], co["p"][0], co["p"][1], co["k"][2]]

    def cv_old(v):
        return "0." if v == 0 else ("1." if v == 1 else opencv_e3(v))

    k_yaml = ", ".join(cv_old(v) for v in Ko[:4]) + ",\n       " + ", ".join(cv_old(v) for v in Ko[4:])
    d_yaml = ", ".join(cv_old(v) for v in Do[:4]) + ",\n       " + ", ".join(cv_old(v) for v in Do[4:])
    # The calibration sample's settings, the same in its YAML and its XML.
    old_settings = [
        ("calibration_Time", '"08/19/11 20:44:38"'),
        ("nrOfFrames", 8),
        ("image_Width", co["size"][0]),
        ("image_Height", co["size"][1]),
        ("board_Width", 9),
        ("board_Height", 6),
        ("square_Size", "50."),
        ("FixAspectRatio", "1."),
    ]
    old_flags = "flags:  +fix_aspectRatio +fix_principal_point +zero_tangent_dist"
    old_settings_yaml = "\n".join(f"{key}: {value}" for key, value in old_settings)
    files["opencv_old_sample.yaml"] = f"""%YAML:1.0
{old_settings_yaml}
# {old_flags}
flagValue: 14
Camera_Matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ {k_yaml} ]
Distortion_Coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ {d_yaml} ]
Avg_Reprojection_Error: {opencv_e3(0.38441346462381665)}
"""
    files["opencv_old_sample.xml"] = f"""<?xml version="1.0"?>
<opencv_storage>
{opencv_xml_scalars(old_settings)}
<!-- {old_flags} -->
<flagValue>14</flagValue>
{opencv_xml_matrix("Camera_Matrix", Ko, 3, cv_old)}
{opencv_xml_matrix("Distortion_Coefficients", Do, 5, cv_old)}
<Avg_Reprojection_Error>{opencv_e3(0.38441346462381665)}</Avg_Reprojection_Error>
</opencv_storage>
"""

    def ros_yaml(cam, model, d, name):
        fx, fy, cx, cy = cam["f"]
        K = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
        P = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        return f"""image_width: {cam['size'][0]}
image_height: {cam['size'][1]}
camera_name: {name}
camera_matrix:
  rows: 3
  cols: 3
  data: [{', '.join(g(v) for v in K)}]
distortion_model: {model}
distortion_coefficients:
  rows: 1
  cols: {len(d)}
  data: [{', '.join(g(v) for v in d)}]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
projection_matrix:
  rows: 3
  cols: 4
  data: [{', '.join(g(v) for v in P)}]
"""

    rp, rr, re = ROS_PLUMB, ROS_RATIONAL, ROS_EQUI
    files["ros_ost.yaml"] = ros_yaml(rp, "plumb_bob", rp["k"][:2] + rp["p"] + [rp["k"][2]],
                                     "narrow_stereo")
    files["ros_rational_ost.yaml"] = ros_yaml(rr, "rational_polynomial",
                                              rr["k"][:2] + rr["p"] + rr["k"][2:], "wide")
    files["ros_equidistant_ost.yaml"] = ros_yaml(re, "equidistant", re["k"], "fisheye")

    def ost_block(cam, name):
        fx, fy, cx, cy = cam["f"]
        d = cam["k"][:2] + cam["p"] + [cam["k"][2]]
        return f"""# oST version 5.0 parameters


[image]

width
{cam['size'][0]}

height
{cam['size'][1]}

[{name}]

camera matrix
{fx:f} 0.000000 {cx:f}
0.000000 {fy:f} {cy:f}
0.000000 0.000000 1.000000

distortion
{' '.join('%f' % v for v in d)}

rectification
1.000000 0.000000 0.000000
0.000000 1.000000 0.000000
0.000000 0.000000 1.000000

projection
{fx:f} 0.000000 {cx:f} 0.000000
0.000000 {fy:f} {cy:f} 0.000000
0.000000 0.000000 1.000000 0.000000

"""
    files["ros_ost.txt"] = (ost_block(ROS_LEFT, "narrow_stereo/left")
                            + ost_block(ROS_RIGHT, "narrow_stereo/right"))

    op = ORB_PINHOLE
    files["orbslam3_old_pinhole.yaml"] = f"""%YAML:1.0

#--------------------------------------------------------------------------------------------
# Camera Parameters. Adjust them!
#--------------------------------------------------------------------------------------------
Camera.type: "PinHole"

# Camera calibration and distortion parameters (OpenCV)
Camera.fx: {g(op['f'][0])}
Camera.fy: {g(op['f'][1])}
Camera.cx: {g(op['f'][2])}
Camera.cy: {g(op['f'][3])}

Camera.k1: {g(op['k'][0])}
Camera.k2: {g(op['k'][1])}
Camera.p1: {g(op['p'][0])}
Camera.p2: {g(op['p'][1])}

Camera.width: {op['size'][0]}
Camera.height: {op['size'][1]}

# Camera frames per second
Camera.fps: 20.0

# Color order of the images (0: BGR, 1: RGB. It is ignored if images are grayscale)
Camera.RGB: 1

# Close/Far threshold. Baseline times.
ThDepth: 35.0

ORBextractor.nFeatures: 1000
ORBextractor.scaleFactor: 1.2
"""
    k1, k2 = ORB_KB1, ORB_KB2

    def orb_cam(n, cam):
        keys = ["fx", "fy", "cx", "cy"]
        lines = [f"Camera{n}.{k}: {g(v)}" for k, v in zip(keys, cam["f"])]
        lines += [f"Camera{n}.k{i + 1}: {g(v)}" for i, v in enumerate(cam["k"])]
        return "\n".join(lines)

    files["orbslam3_kb8_stereo.yaml"] = f"""%YAML 1.0
---

#--------------------------------------------------------------------------------------------
# Camera Parameters. Adjust them!
#--------------------------------------------------------------------------------------------
File.version: "1.0"

Camera.type: "KannalaBrandt8"

# Left Camera calibration and distortion parameters (OpenCV)
{orb_cam(1, k1)}

# Right Camera calibration and distortion parameters (OpenCV)
{orb_cam(2, k2)}

# Transformation matrix from right camera to left camera
Stereo.T_c1_c2: !!opencv-matrix
  rows: 4
  cols: 4
  dt: f
  data: [0.999997256477881, 0.002312067192424, 0.000376008102415, -0.101077454189,
         -0.002317135723281, 0.999898048506644, 0.014089835846648, 0.001980121712072,
         -0.000343393120525, -0.014090668452714, 0.999900662637729, 0.001162621635019,
         0, 0, 0, 1.000000000000000]

# Lapping area between images
Camera1.overlappingBegin: 0
Camera1.overlappingEnd: 511
Camera2.overlappingBegin: 0
Camera2.overlappingEnd: 511

Camera.width: {k1['size'][0]}
Camera.height: {k1['size'][1]}
Camera.fps: 20
Camera.RGB: 1
Stereo.ThDepth: 40.0
"""
    for name, text in files.items():
        (calib / name).write_text(text)
    return files


def oracle(rng):
    cases = []

    def add(file, fmt, camera, fov_deg, model, pts, px, folds=False):
        assert np.isfinite(px).all()
        cases.append(dict(file=file, format=fmt, camera=camera, fov_deg=fov_deg, model=model,
                          folds=folds, rays=pts.tolist(), pixels=px.tolist()))

    # Kalibr omni-radtan: Mei's domain z > -|p| / xi (xi > 1): up to 120 deg < 125.5.
    pts = rays(rng, 120.0)
    add("kalibr_omni_fov.yaml", "kalibr", 0, None, "mei", pts, mei_reference(OMNI, pts))
    pts = rays(rng, 85.0)
    add("kalibr_omni_fov.yaml", "kalibr", 1, None, "fov", pts, fov_reference(KALIBR_FOV, pts))

    r8 = dict(RADTAN8)
    pts = pinhole_rays(rng, r8, 75.0, bound=r8["rpmax"])
    add("basalt_radtan8.json", "basalt", 0, None, "pinhole-radtan", pts, opencv_radtan(r8, pts))
    pts = rays(rng, 85.0)
    add("basalt_radtan8.json", "basalt", 1, None, "fov", pts, fov_reference(BASALT_FOV, pts))

    for cam_id, cam, folds in [(1, FULL_OPENCV, False), (2, FOLDING, True)]:
        pts = pinhole_rays(rng, cam, 60.0)
        assert folds_inside(cam) == folds
        add("colmap_full_opencv.txt", "colmap", cam_id, None, "pinhole-radtan", pts,
            opencv_radtan(cam, pts), folds)
    pts = rays(rng, 85.0)
    add("colmap_full_opencv.txt", "colmap", 3, None, "fov", pts, fov_reference(COLMAP_FOV, pts))

    pts = pinhole_rays(rng, CV_RATIONAL, 50.0)
    add("opencv_rational.xml", "opencv", None, None, "pinhole-radtan", pts,
        opencv_radtan(CV_RATIONAL, pts))
    pts = pinhole_rays(rng, CV_OLD, 40.0)
    for name in ["opencv_old_sample.yaml", "opencv_old_sample.xml"]:
        add(name, "opencv", None, None, "pinhole-radtan", pts, opencv_radtan(CV_OLD, pts),
            folds_inside(CV_OLD))

    pts = pinhole_rays(rng, ROS_PLUMB, 50.0)
    add("ros_ost.yaml", "ros", None, None, "pinhole-radtan", pts, opencv_radtan(ROS_PLUMB, pts))
    pts = pinhole_rays(rng, ROS_RATIONAL, 60.0)
    add("ros_rational_ost.yaml", "ros", None, None, "pinhole-radtan", pts,
        opencv_radtan(ROS_RATIONAL, pts))
    pts = rays(rng, 85.0)
    add("ros_equidistant_ost.yaml", "ros", None, None, "kannala-brandt", pts,
        opencv_fisheye(ROS_EQUI, pts))
    for n, cam in enumerate([ROS_LEFT, ROS_RIGHT]):
        # ost.txt prints 6 decimals: the oracle uses the values as printed.
        printed = dict(cam)
        printed["f"] = [float("%f" % v) for v in cam["f"]]
        printed["k"] = [float("%f" % v) for v in cam["k"]]
        printed["p"] = [float("%f" % v) for v in cam["p"]]
        pts = pinhole_rays(rng, printed, 50.0)
        add("ros_ost.txt", "ros", n, None, "pinhole-radtan", pts, opencv_radtan(printed, pts))

    pts = pinhole_rays(rng, ORB_PINHOLE, 50.0)
    add("orbslam3_old_pinhole.yaml", "orbslam3", None, None, "pinhole-radtan", pts,
        opencv_radtan(ORB_PINHOLE, pts))
    for n, cam in enumerate([ORB_KB1, ORB_KB2]):
        pts = rays(rng, 85.0)
        add("orbslam3_kb8_stereo.yaml", "orbslam3", n, None, "kannala-brandt", pts,
            opencv_fisheye(cam, pts))
    return cases


def main():
    root = Path(sys.argv[1] if len(sys.argv) > 1 else "tests/golden")
    calib = root / "calib"
    calib.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(47)
    cases = oracle(rng)
    write_files(calib)
    doc = {
        "generator": f"tools/make_calib_fixtures.py, OpenCV {cv2.__version__}, NumPy {np.__version__}",
        "pixel_convention": "top-left pixel centre at (0, 0), OpenCV's",
        "cases": cases,
    }
    (root / "calib_oracle.json").write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {len(cases)} cameras to {root / 'calib_oracle.json'}")


if __name__ == "__main__":
    main()
