#!/usr/bin/env python3
"""Golden fixtures from independent oracles (torchvision, OpenCV) for the integration tests.

Usage (from the crate root):

    .venv/bin/python tools/make_fixtures.py tests/golden

Writes, deterministically (fixed seeds):

- ``deform_conv2d.safetensors``: ``torchvision.ops.deform_conv2d`` outputs and gradients (input,
  weight, bias, and the per-item offsets) for a set of layer geometries (read by
  ``tests/integration/oracle_torchvision.rs``);
- ``opencv_fisheye.json``: ``cv2.fisheye.projectPoints`` / ``cv2.fisheye.undistortPoints`` for two
  Kannala-Brandt cameras (read by ``tests/integration/oracle_opencv.rs``);
- ``opencv_radtan.json``: ``cv2.projectPoints`` / ``cv2.undistortPoints`` for two pinhole
  cameras with OpenCV's radial-tangential distortion (read by
  ``tests/integration/oracle_opencv_radtan.rs``).

Every oracle value is double-checked here before it is written: the deformable convolution
against a direct NumPy loop and against torchvision in float32, the fisheye values against a
direct evaluation of the Kannala-Brandt polynomial, the radial-tangential values against a
direct evaluation of OpenCV's distortion formula. A failed check aborts without writing.
"""

import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import safetensors
import safetensors.torch
import torch
import torchvision
from torchvision.ops import deform_conv2d

# ----------------------------------------------------------------------------------------------
# deform_conv2d
# ----------------------------------------------------------------------------------------------

# (name, batch, c_in, c_out, h, w, kh, kw, stride, padding, dilation, groups, bias, per_item)
DEFORM_CASES = [
    ("3x3 s1 p1 d1 g1 bias", 2, 3, 4, 8, 8, 3, 3, (1, 1), (1, 1), (1, 1), 1, True, False),
    ("3x3 s2 p1 d1 g1 no bias", 2, 3, 5, 10, 10, 3, 3, (2, 2), (1, 1), (1, 1), 1, False, False),
    ("3x3 s1 p2 d2 g1 bias", 1, 4, 3, 9, 9, 3, 3, (1, 1), (2, 2), (2, 2), 1, True, False),
    ("3x3 s1 p1 d1 g2 bias", 2, 4, 6, 7, 7, 3, 3, (1, 1), (1, 1), (1, 1), 2, True, False),
    ("5x5 s1 p2 g1 no bias", 1, 2, 3, 11, 11, 5, 5, (1, 1), (2, 2), (1, 1), 1, False, False),
    ("3x3 s2 p0 d1 9x13 g1 bias", 2, 3, 4, 9, 13, 3, 3, (2, 2), (0, 0), (1, 1), 1, True, False),
    ("1x3 s(1,2) p(0,1) 10x12 g1 bias", 2, 3, 2, 10, 12, 1, 3, (1, 2), (0, 1), (1, 1), 1, True, False),
    ("3x1 s1 p(1,0) d(2,1) g1 bias", 1, 2, 3, 12, 7, 3, 1, (1, 1), (1, 0), (2, 1), 1, True, False),
    ("3x3 s1 p1 d1 g1 bias per-item offsets", 2, 3, 4, 8, 9, 3, 3, (1, 1), (1, 1), (1, 1), 1, True, True),
    ("3x3 s1 p1 d1 g4 bias, 2 channels per group", 2, 8, 8, 6, 6, 3, 3, (1, 1), (1, 1), (1, 1), 4, True, False),
]

OFFSET_STD_PX = 2.0


def out_size(n, k, s, p, d):
    return (n + 2 * p - d * (k - 1) - 1) // s + 1


def bilinear_zeros(img, y, x):
    """torchvision's bilinear sample of img [H, W] at (y, x): 0 when y <= -1, y >= H, x <= -1 or
    x >= W; otherwise each of the four corners that lies outside contributes 0."""
    h, w = img.shape
    if y <= -1 or y >= h or x <= -1 or x >= w:
        return 0.0
    y0, x0 = math.floor(y), math.floor(x)
    ly, lx = y - y0, x - x0
    total = 0.0
    for yy, wy in ((y0, 1 - ly), (y0 + 1, ly)):
        for xx, wx in ((x0, 1 - lx), (x0 + 1, lx)):
            if 0 <= yy < h and 0 <= xx < w:
                total += wy * wx * img[yy, xx]
    return total


def naive_deform_conv2d(inp, off, weight, bias, stride, padding, dilation, groups):
    """Direct loop over the definition, float64 NumPy. off is [B, 2*kh*kw, Ho, Wo] with the pair
    (dy, dx) per tap in row-major tap order."""
    b, c_in, h, w = inp.shape
    c_out, c_pg, kh, kw = weight.shape
    ho, wo = off.shape[2], off.shape[3]
    out_pg = c_out // groups
    out = np.zeros((b, c_out, ho, wo))
    for n in range(b):
        # columns[c, tap, oy, ox]
        cols = np.zeros((c_in, kh * kw, ho, wo))
        for i in range(kh):
            for j in range(kw):
                t = i * kw + j
                for oy in range(ho):
                    for ox in range(wo):
                        y = oy * stride[0] - padding[0] + i * dilation[0] + off[n, 2 * t, oy, ox]
                        x = ox * stride[1] - padding[1] + j * dilation[1] + off[n, 2 * t + 1, oy, ox]
                        for c in range(c_in):
                            cols[c, t, oy, ox] = bilinear_zeros(inp[n, c], y, x)
        for co in range(c_out):
            g = co // out_pg
            chunk = cols[g * c_pg:(g + 1) * c_pg].reshape(c_pg * kh * kw, ho, wo)
            out[n, co] = np.tensordot(weight[co].reshape(-1), chunk, axes=1)
            if bias is not None:
                out[n, co] += bias[co]
    return out


def make_deform_fixtures(path):
    gen = torch.Generator().manual_seed(20240611)
    tensors = {}
    n_outside = 0
    n_samples = 0
    for idx, (name, b, c_in, c_out, h, w, kh, kw, stride, padding, dilation, groups, has_bias,
              per_item) in enumerate(DEFORM_CASES):
        assert b <= 2 and c_in <= 8 and c_out <= 8 and h <= 16 and w <= 16, name
        ho = out_size(h, kh, stride[0], padding[0], dilation[0])
        wo = out_size(w, kw, stride[1], padding[1], dilation[1])
        taps = kh * kw
        # Float32 values, then computed in float64 so the reference carries no float32 round-off.
        inp = torch.randn(b, c_in, h, w, generator=gen)
        weight = torch.randn(c_out, c_in // groups, kh, kw, generator=gen) / math.sqrt(
            c_in // groups * taps)
        bias = torch.randn(c_out, generator=gen) if has_bias else None
        off_shape = (b, 2 * taps, ho, wo) if per_item else (2 * taps, ho, wo)
        offset = torch.randn(*off_shape, generator=gen) * OFFSET_STD_PX
        probe = torch.randn(b, c_out, ho, wo, generator=gen)
        off_b = offset if per_item else offset.unsqueeze(0).expand(b, -1, -1, -1)

        def run(dtype):
            # clone(): .to(float32) would return the fixture tensor itself.
            x = inp.to(dtype).clone().requires_grad_(True)
            wt = weight.to(dtype).clone().requires_grad_(True)
            bs = bias.to(dtype).clone().requires_grad_(True) if has_bias else None
            off = off_b.to(dtype).contiguous().clone().requires_grad_(True)
            out = deform_conv2d(x, off, wt, bs, stride=stride, padding=padding,
                                dilation=dilation)
            (out * probe.to(dtype)).sum().backward()
            gb = bs.grad if has_bias else None
            return out.detach(), x.grad, wt.grad, gb, off.grad

        out64, gi64, gw64, gb64, go64 = run(torch.float64)
        out32, gi32, gw32, gb32, _ = run(torch.float32)

        # Check 1: torchvision float32 agrees with torchvision float64.
        for what, a, r in (("output", out32, out64), ("grad_input", gi32, gi64),
                           ("grad_weight", gw32, gw64)) + ((("grad_bias", gb32, gb64),)
                                                            if has_bias else ()):
            rel = (a.double() - r).abs().max() / r.abs().max().clamp_min(1e-30)
            assert rel < 1e-5, f"{name} {what}: float32 vs float64 rel {rel:.3e}"

        # Check 2: the forward agrees with a direct NumPy loop over the definition.
        naive = naive_deform_conv2d(inp.double().numpy(), off_b.double().numpy(),
                                    weight.double().numpy(),
                                    bias.double().numpy() if has_bias else None,
                                    stride, padding, dilation, groups)
        err = np.abs(naive - out64.numpy()).max()
        assert err < 1e-12, f"{name}: torchvision vs naive loop {err:.3e}"

        # Check 3: grad_input agrees with central differences of the float64 loss.
        # (grad_weight / grad_bias are linear in the output and covered by the same loss.)
        x = inp.double()
        for k in torch.randint(0, x.numel(), (5,), generator=gen).tolist():
            e = torch.zeros_like(x).view(-1)
            e[k] = 1e-6
            e = e.view_as(x)

            def loss(xx):
                return (deform_conv2d(xx, off_b.double().contiguous(), weight.double(),
                                      bias.double() if has_bias else None, stride=stride,
                                      padding=padding, dilation=dilation)
                        * probe.double()).sum().item()

            fd = (loss(x + e) - loss(x - e)) / 2e-6
            assert abs(fd - gi64.view(-1)[k].item()) < 1e-6, f"{name}: grad_input fd at {k}"

        # Check 4: grad_offset (per item, [B, 2*kh*kw, Ho, Wo]) agrees with central differences.
        off64 = off_b.double().contiguous()
        # (Its own generator: the fixture's random draws stay those of the other checks.)
        fd_gen = torch.Generator().manual_seed(1000 + idx)
        for k in torch.randint(0, off64.numel(), (5,), generator=fd_gen).tolist():
            e = torch.zeros_like(off64).view(-1)
            e[k] = 1e-6
            e = e.view_as(off64)

            def loss_off(oo):
                return (deform_conv2d(inp.double(), oo, weight.double(),
                                      bias.double() if has_bias else None, stride=stride,
                                      padding=padding, dilation=dilation)
                        * probe.double()).sum().item()

            fd = (loss_off(off64 + e) - loss_off(off64 - e)) / 2e-6
            assert abs(fd - go64.view(-1)[k].item()) < 1e-5, f"{name}: grad_offset fd at {k}"

        # Statistics: how many sampling locations fall fully outside the map.
        ys = (torch.arange(ho).view(1, ho, 1) * stride[0] - padding[0]
              + (torch.arange(taps) // kw).view(taps, 1, 1) * dilation[0])
        xs = (torch.arange(wo).view(1, 1, wo) * stride[1] - padding[1]
              + (torch.arange(taps) % kw).view(taps, 1, 1) * dilation[1])
        off4 = off_b.view(b, taps, 2, ho, wo)
        sy = ys + off4[:, :, 0]
        sx = xs + off4[:, :, 1]
        n_outside += int(((sy <= -1) | (sy >= h) | (sx <= -1) | (sx >= w)).sum())
        n_samples += sy.numel()

        c = f"c{idx}"
        tensors[f"{c}.input"] = inp
        tensors[f"{c}.offset"] = offset.contiguous()
        tensors[f"{c}.weight"] = weight
        if has_bias:
            tensors[f"{c}.bias"] = bias
            tensors[f"{c}.grad_bias"] = gb64.float()
        tensors[f"{c}.probe"] = probe
        tensors[f"{c}.output"] = out64.float()
        tensors[f"{c}.grad_input"] = gi64.float()
        tensors[f"{c}.grad_weight"] = gw64.float()
        tensors[f"{c}.grad_offset"] = go64.float()
        tensors[f"{c}.meta"] = torch.tensor(
            [stride[0], stride[1], padding[0], padding[1], dilation[0], dilation[1], groups,
             int(has_bias)], dtype=torch.int64)
        print(f"  {c}: {name}: input {list(inp.shape)} offset {list(offset.shape)} "
              f"output {list(out64.shape)}")

    # One metadata key: safetensors stores the metadata as a hash map, so with several keys their
    # order in the file (and so the file's bytes) would change from run to run.
    about = {
        "generator": "tools/make_fixtures.py",
        "oracle": f"torchvision.ops.deform_conv2d, torchvision {torchvision.__version__}, "
                  f"torch {torch.__version__}",
        "precision": "float32 inputs; computed in float64 by torchvision, stored as float32",
        "meta_layout": "[stride_h, stride_w, pad_h, pad_w, dil_h, dil_w, groups, has_bias]",
        "cases": {f"c{i}": c[0] for i, c in enumerate(DEFORM_CASES)},
    }
    metadata = {"about": json.dumps(about, indent=1)}
    safetensors.torch.save_file(tensors, str(path), metadata=metadata)
    print(f"wrote {path}: {len(DEFORM_CASES)} cases, {n_outside}/{n_samples} sampling "
          f"locations fully outside the input")
    assert n_outside > 0.05 * n_samples


# ----------------------------------------------------------------------------------------------
# OpenCV fisheye
# ----------------------------------------------------------------------------------------------

CAMERAS = [
    {
        # The paper's F195 calibration (data/cameras/f195.toml).
        "name": "F195",
        "fx": 287.0, "fy": 287.0, "cx": 540.0, "cy": 480.0,
        "k": [3.37012024344156e-19, -3.543830680552053e-05, 9.999999999924497e-08,
              -6.883696004705416e-11],
        "width": 1080, "height": 960,
    },
    {
        # A made-up, strongly distorted lens with fx != fy and a fractional principal point.
        "name": "strong-distortion test camera",
        "fx": 310.0, "fy": 305.0, "cx": 512.3, "cy": 470.8,
        "k": [0.05, -0.01, 0.002, -0.0003],
        "width": 1024, "height": 944,
    },
]

N_POINTS = 200
PROJECT_THETA_MAX_DEG = 85.0
UNPROJECT_THETA_MAX_DEG = 80.0
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def distort(k, theta):
    t2 = theta * theta
    return theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))


def distort_derivative(k, theta):
    t2 = theta * theta
    return 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))


def dump_json(value, indent=""):
    """JSON with one point (a list of numbers) per line; floats as Python's shortest repr, which
    reads back to the same float64."""
    inner = indent + " "
    if isinstance(value, dict):
        items = [f"{inner}{json.dumps(k)}: {dump_json(v, inner)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(value, list) and any(isinstance(v, (list, dict)) for v in value):
        return "[\n" + ",\n".join(inner + dump_json(v, inner) for v in value) + "\n" + indent + "]"
    return json.dumps(value)


def camera_matrix(cam):
    """OpenCV's K of a camera dict (fx, fy, cx, cy)."""
    return np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]])


def random_rays(rng, theta_max_deg):
    """N_POINTS rays with theta uniform in [0, theta_max_deg] (the first on the axis), random
    azimuth and length in [0.05, 20]."""
    theta = np.radians(rng.uniform(0.0, theta_max_deg, N_POINTS))
    theta[0] = 0.0
    phi = rng.uniform(-math.pi, math.pi, N_POINTS)
    length = rng.uniform(0.05, 20.0, N_POINTS)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                     np.cos(theta)], axis=1) * length[:, None]


def check_round_trip(project_points, K, D, normalized, pix, name):
    """The normalized points (x/z, y/z) project back onto their pixels with `project_points`
    (cv2.fisheye.projectPoints or cv2.projectPoints), within 1e-9 px."""
    back, _ = project_points(
        np.concatenate([normalized, np.ones((N_POINTS, 1))], axis=1).reshape(-1, 1, 3),
        np.zeros(3), np.zeros(3), K, D)
    err = np.abs(back.reshape(-1, 2) - pix).max()
    assert err < 1e-9, f"{name}: undistort/project round trip {err:.3e} px"


def camera_entry(cam, project, unproject):
    """A camera of a fixture file: its fields, then its `project` and `unproject` records."""
    print(f"  {cam['name']}: {N_POINTS} projections, {N_POINTS} unprojections")
    return {**cam, "project": project, "unproject": unproject}


def write_fixture(path, generator, cams):
    """Writes `{"generator": ..., "cameras": [...]}` with `dump_json`."""
    path.write_text(dump_json({"generator": generator, "cameras": cams}) + "\n")
    print(f"wrote {path}")


def make_fisheye_fixtures(path):
    rng = np.random.default_rng(19700101)
    out_cams = []
    for cam in CAMERAS:
        k = np.array(cam["k"])
        # d must increase on [0, pi/2] (checked densely), so that every front ray has one pixel.
        grid = np.linspace(0.0, math.pi / 2, 100001)
        assert (distort_derivative(k, grid) > 0).all(), cam["name"]
        assert (np.diff(distort(k, grid)) > 0).all(), cam["name"]
        K = camera_matrix(cam)
        D = k.reshape(4, 1)

        # Project: rays in the front hemisphere, theta uniform in [0, 85] deg (plus the axis),
        # random azimuth and length.
        rays = random_rays(rng, PROJECT_THETA_MAX_DEG)
        pixels, _ = cv2.fisheye.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                              K, D)
        pixels = pixels.reshape(-1, 2)
        # Double check against the polynomial evaluated here.
        rho = np.hypot(rays[:, 0], rays[:, 1])
        th = np.arctan2(rho, rays[:, 2])
        r_d = distort(k, th)
        scale = np.where(rho > 0, r_d / np.where(rho > 0, rho, 1), 0)
        mine = np.stack([cam["fx"] * scale * rays[:, 0] + cam["cx"],
                         cam["fy"] * scale * rays[:, 1] + cam["cy"]], axis=1)
        err = np.abs(mine - pixels).max()
        assert err < 1e-9, f"{cam['name']}: projectPoints vs polynomial {err:.3e} px"

        # Unproject: pixels inside the image whose ray is within 80 deg of the axis (OpenCV's
        # solver clamps theta_d to pi/2 and is not meant for wider angles).
        r_d_max = distort(k, math.radians(UNPROJECT_THETA_MAX_DEG))
        pix = []
        while len(pix) < N_POINTS:
            u = rng.uniform(-0.5, cam["width"] - 0.5)
            v = rng.uniform(-0.5, cam["height"] - 0.5)
            if math.hypot((u - cam["cx"]) / cam["fx"], (v - cam["cy"]) / cam["fy"]) < r_d_max:
                pix.append([u, v])
        pix[0] = [cam["cx"], cam["cy"]]
        pix = np.array(pix)
        normalized = cv2.fisheye.undistortPoints(pix.reshape(-1, 1, 2), K, D,
                                                 criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
        # OpenCV marks non-converged points with -1e6; none may be.
        assert np.isfinite(normalized).all() and (np.abs(normalized) < 1e5).all(), cam["name"]
        # Double check: the normalized point (x/z, y/z) projects back onto the pixel.
        check_round_trip(cv2.fisheye.projectPoints, K, D, normalized, pix, cam["name"])

        out_cams.append(camera_entry(
            cam,
            {"theta_max_deg": PROJECT_THETA_MAX_DEG, "rays": rays.tolist(),
             "pixels": pixels.tolist()},
            {"theta_max_deg": UNPROJECT_THETA_MAX_DEG, "criteria": "COUNT|EPS, 100, 1e-14",
             "pixels": pix.tolist(), "normalized": normalized.tolist()}))

    write_fixture(path, f"tools/make_fixtures.py with OpenCV {cv2.__version__} "
                        f"(cv2.fisheye.projectPoints, cv2.fisheye.undistortPoints), "
                        f"NumPy {np.__version__}, float64", out_cams)


# ----------------------------------------------------------------------------------------------
# OpenCV standard model (radial-tangential, k1 k2 p1 p2 k3)
# ----------------------------------------------------------------------------------------------

RADTAN_CAMERAS = [
    {
        # EuRoC MAV cam0 (sensor.yaml; Kalibr pinhole-radtan, so k3 = 0), as in
        # data/cameras/radtan_example.toml.
        "name": "EuRoC cam0",
        "fx": 458.654, "fy": 457.296, "cx": 367.215, "cy": 248.375,
        "k": [-0.28340811, 0.07395907, 0.0], "p": [0.00019359, 1.76187114e-05],
        "width": 752, "height": 480,
    },
    {
        # Made up: all five coefficients non-zero, strong tangential terms, fx != fy, a
        # fractional principal point.
        "name": "five-coefficient test camera",
        "fx": 610.0, "fy": 604.5, "cx": 331.7, "cy": 242.2,
        "k": [-0.21, 0.09, -0.012], "p": [0.004, -0.003],
        "width": 640, "height": 480,
    },
]

# Rays up to 40 deg off-axis (r = tan(theta) <= 0.84 on the z = 1 plane) for projection; the
# distortion must be invertible there (checked below).
RADTAN_PROJECT_THETA_MAX_DEG = 40.0
RADTAN_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def radtan_distort(cam, x, y):
    k1, k2, k3 = cam["k"]
    p1, p2 = cam["p"]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def make_radtan_fixtures(path):
    rng = np.random.default_rng(19700102)
    out_cams = []
    for cam in RADTAN_CAMERAS:
        K = camera_matrix(cam)
        D = np.array([cam["k"][0], cam["k"][1], cam["p"][0], cam["p"][1], cam["k"][2]])

        # The distortion map must not fold over the projected range nor over the image: its
        # Jacobian determinant (central differences) stays positive on a dense grid.
        r_max = 1.3 * math.tan(math.radians(RADTAN_PROJECT_THETA_MAX_DEG))
        g = np.linspace(-r_max, r_max, 801)
        gx, gy = np.meshgrid(g, g)
        h = 1e-6
        ax, ay = radtan_distort(cam, gx + h, gy)
        bx, by = radtan_distort(cam, gx - h, gy)
        cx_, cy_ = radtan_distort(cam, gx, gy + h)
        dx_, dy_ = radtan_distort(cam, gx, gy - h)
        det = ((ax - bx) * (cy_ - dy_) - (ay - by) * (cx_ - dx_)) / (4 * h * h)
        assert (det > 0).all(), cam["name"]

        # Project: rays within 40 deg of the axis (plus the axis), random azimuth and length.
        rays = random_rays(rng, RADTAN_PROJECT_THETA_MAX_DEG)
        pixels, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
        pixels = pixels.reshape(-1, 2)
        # Double check against the formula evaluated here.
        xd, yd = radtan_distort(cam, rays[:, 0] / rays[:, 2], rays[:, 1] / rays[:, 2])
        mine = np.stack([cam["fx"] * xd + cam["cx"], cam["fy"] * yd + cam["cy"]], axis=1)
        err = np.abs(mine - pixels).max()
        assert err < 1e-9, f"{cam['name']}: projectPoints vs formula {err:.3e} px"

        # Unproject: pixels anywhere in the image (the first at the principal point), solved by
        # OpenCV's fixed-point iteration run to convergence (OpenCV 5's undistortPoints takes the
        # criteria; without them it stops after 5 iterations).
        pix = np.stack([rng.uniform(-0.5, cam["width"] - 0.5, N_POINTS),
                        rng.uniform(-0.5, cam["height"] - 0.5, N_POINTS)], axis=1)
        pix[0] = [cam["cx"], cam["cy"]]
        normalized = cv2.undistortPoints(pix.reshape(-1, 1, 2), K, D, None, None, None,
                                         RADTAN_UNDISTORT_CRITERIA).reshape(-1, 2)
        assert np.isfinite(normalized).all(), cam["name"]
        # Double check: the normalized point projects back onto the pixel.
        check_round_trip(cv2.projectPoints, K, D, normalized, pix, cam["name"])

        out_cams.append(camera_entry(
            cam,
            {"theta_max_deg": RADTAN_PROJECT_THETA_MAX_DEG, "rays": rays.tolist(),
             "pixels": pixels.tolist()},
            {"criteria": "COUNT|EPS, 100, 1e-14", "pixels": pix.tolist(),
             "normalized": normalized.tolist()}))

    write_fixture(path, f"tools/make_fixtures.py with OpenCV {cv2.__version__} "
                        f"(cv2.projectPoints, cv2.undistortPoints with criteria), "
                        f"NumPy {np.__version__}, float64", out_cams)


def main():
    if len(sys.argv) != 2:
        sys.exit(f"usage: {sys.argv[0]} OUT_DIR   (e.g. tests/golden)")
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    torch.use_deterministic_algorithms(True)
    print(f"torch {torch.__version__}, torchvision {torchvision.__version__}, "
          f"OpenCV {cv2.__version__}, NumPy {np.__version__}, safetensors {safetensors.__version__}")
    make_deform_fixtures(out / "deform_conv2d.safetensors")
    make_fisheye_fixtures(out / "opencv_fisheye.json")
    make_radtan_fixtures(out / "opencv_radtan.json")


if __name__ == "__main__":
    main()
