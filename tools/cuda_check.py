"""The Python package's CUDA path on a GPU machine: its tests, then timings.

    python tools/cuda_check.py --out DIR            # on a machine with CUDA
    python tools/cuda_check.py --out DIR --device cpu --small   # the same script, CPU, small

Needs torch, torchvision, numpy, pytest, safetensors and the calibconv wheel installed (the
README's "From Python" section gives the commands used on a GPU machine without a Rust
toolchain: the abi3 wheel is built elsewhere and installed there with ``--no-deps``).

1. pytest ``python/tests/test_devices.py`` (CPU float32; CUDA float32 and float64; all against
   a float64 CPU reference) and ``python/tests/test_torch.py``; JUnit XML to DIR/pytest.xml.
   Skipped with ``--no-tests``.
2. Timings on ``--device``, each case in its own child process (a CUDA fault such as an illegal
   memory access leaves a process's CUDA context unusable: the case is recorded as failed with
   the error's line and the next one runs), interleaved (A, B, A, B, ...), medians of ``--reps``
   after one warm-up each, the device synchronised around every call:
   - one layer, ``torchvision.ops.deform_conv2d`` with F195 offsets (what ``CalibratedConv2d``
     runs) against ``conv2d``, forward and forward+backward, at the 3x3 layers of the classic
     U-Net (base 64, batch 8) at the paper's 960x1088 input;
   - the whole classic U-Net (``tools/reference_unet.py``, transposed up-sampling), one training
     step (forward, cross-entropy over 2 classes, backward, SGD step), calibrated by
     ``calibconv.torch.calibrate`` against standard, batch 8 at 960x1088, 480x544 and 128x144.
3. Peak memory of each U-Net step in its own pass after the timings
   (``torch.cuda.max_memory_allocated``; CUDA only).
Writes DIR/cuda-check.json (environment, test counts, every median and ratio) and prints a table.
The exit status is pytest's when it fails, else 0.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch
import torchvision
from torch import nn
from torchvision.ops import deform_conv2d

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import reference_unet  # noqa: E402

F195 = ROOT / "data" / "cameras" / "f195.toml"


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def interleaved(fns: dict, device: torch.device, reps: int) -> dict:
    """Median seconds of each callable, called in turn ``reps`` times after one warm-up each."""
    for f in fns.values():
        f()
    sync(device)
    times = {k: [] for k in fns}
    for _ in range(reps):
        for k, f in fns.items():
            sync(device)
            t = time.perf_counter()
            f()
            sync(device)
            times[k].append(time.perf_counter() - t)
    return {k: statistics.median(v) for k, v in times.items()}


def classic_layers(h: int, w: int, base: int = 64):
    """(C_in, C_out, H, W) of the distinct 3x3 layers of the classic U-Net at an h x w input."""
    layers, c = [(3, base, h, w), (base, base, h, w)], base
    for level in range(1, 5):
        hh, ww = h >> level, w >> level
        layers += [(c, 2 * c, hh, ww), (2 * c, 2 * c, hh, ww)]
        c *= 2
    for level in range(3, -1, -1):  # decoder: cat(skip, up) = c channels -> c / 2
        hh, ww = h >> level, w >> level
        layers += [(c, c // 2, hh, ww), (c // 2, c // 2, hh, ww)]
        c //= 2
    return list(dict.fromkeys(layers))


def layer_name(cin, cout, h, w) -> str:
    return f"{cin}->{cout}@{h}x{w}"


def time_layer(cin, cout, h, w, batch, device, reps):
    import calibconv

    off = torch.as_tensor(calibconv.offsets(str(F195), (h, w))).to(device).unsqueeze(0)
    off = off.expand(batch, -1, -1, -1)
    x = torch.randn(batch, cin, h, w, device=device, requires_grad=True)
    wt = (torch.randn(cout, cin, 3, 3, device=device) * 0.1).requires_grad_(True)
    g = torch.randn(batch, cout, h, w, device=device)

    def conv():
        return nn.functional.conv2d(x, wt, padding=1)

    def calibrated():
        return deform_conv2d(x, off, wt, padding=(1, 1))

    def fb(f):
        def run():
            x.grad = wt.grad = None
            f().backward(g)
        return run

    with torch.no_grad():
        fwd = interleaved({"conv2d": conv, "calibrated": calibrated}, device, reps)
    both = interleaved({"conv2d": fb(conv), "calibrated": fb(calibrated)}, device, reps)
    return {
        "layer": layer_name(cin, cout, h, w),
        "batch": batch,
        "forward_s": fwd,
        "forward_backward_s": both,
        "forward_ratio": fwd["calibrated"] / fwd["conv2d"],
        "forward_backward_ratio": both["calibrated"] / both["conv2d"],
    }


def unet_steps(h, w, batch, device, base):
    """Standard and calibrated classic U-Nets with the same weights, and a training step each."""
    from calibconv.torch import calibrate

    torch.manual_seed(0)
    std = reference_unet.UNet(3, 2, bilinear=False, base=base).to(device)
    cal = reference_unet.UNet(3, 2, bilinear=False, base=base).to(device)
    cal.load_state_dict(std.state_dict())
    calibrate(cal, F195, (h, w))
    x = torch.randn(batch, 3, h, w, device=device)
    y = torch.randint(0, 2, (batch, h, w), device=device)

    def step_of(model):
        opt = torch.optim.SGD(model.parameters(), lr=1e-3)

        def step():
            opt.zero_grad(set_to_none=True)
            nn.functional.cross_entropy(model(x), y).backward()
            opt.step()
        return step

    return {"standard": step_of(std), "calibrated": step_of(cal)}


def time_unet(h, w, batch, base, device, reps):
    row = {"input": f"{h}x{w}", "batch": batch, "base": base}
    steps = unet_steps(h, w, batch, device, base)
    t = interleaved(steps, device, reps)
    row.update(step_s=t, ratio=t["calibrated"] / t["standard"])
    if device.type == "cuda":  # memory in its own pass, one step each after a reset
        peak = {}
        for k, f in steps.items():
            sync(device)
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats(device)
            f()
            sync(device)
            peak[k] = torch.cuda.max_memory_allocated(device)
        row["peak_bytes"] = peak
        row["peak_ratio"] = peak["calibrated"] / peak["standard"]
    return row


def one_case(case: list, common: list) -> dict:
    """Times one case in a child process: a CUDA fault (an illegal memory access leaves the
    process's CUDA context unusable) or running out of memory is recorded, and the next case
    runs in a fresh process. The row is the child's last line of output."""
    import subprocess

    kind, *args = case
    name = layer_name(*args[:4]) if kind == "layer" else f"{args[0]}x{args[1]}"
    r = subprocess.run([sys.executable, __file__, "--case", json.dumps(case), *common],
                       capture_output=True, text=True)
    lines = r.stdout.strip().splitlines()
    if r.returncode == 0 and lines:
        return json.loads(lines[-1])
    # The exception's own line ("torch.AcceleratorError: CUDA error: an illegal memory access
    # was encountered"), not the hints printed after it.
    import re

    errors = [ln for ln in r.stderr.splitlines() if re.match(r"[\w.]+(Error|Exception): ", ln)]
    errors = errors or r.stderr.strip().splitlines()[-1:]
    key = "layer" if kind == "layer" else "input"
    return {key: name, "batch": args[-1] if kind == "layer" else args[2],
            "error": errors[-1] if errors else f"exit status {r.returncode}"}


def run_tests(out: Path) -> dict:
    import pytest

    xml = out / "pytest.xml"
    files = [str(ROOT / "python" / "tests" / f) for f in ("test_devices.py", "test_torch.py")]
    status = pytest.main(["-q", "-p", "no:cacheprovider", f"--junitxml={xml}", *files])
    import xml.etree.ElementTree as ET

    suite = ET.parse(xml).getroot()
    suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
    counts = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
    cases = [f"{c.get('classname')}::{c.get('name')}" for c in suite.iter("testcase")]
    return {"exit_status": int(status), **counts,
            "cuda_cases": sum("cuda" in c for c in cases)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--small", action="store_true",
                    help="tiny shapes (batch 2; layers at 32x36 and 16x18, a U-Net of base 4 at "
                    "64x72): checks the script itself")
    ap.add_argument("--no-tests", action="store_true")
    ap.add_argument("--case", help=argparse.SUPPRESS)  # one timing case (a child process)
    a = ap.parse_args(argv)
    device = torch.device(a.device)
    torch.backends.cudnn.benchmark = False  # the default, stated: cases time fixed algorithms
    if a.case:
        kind, *args = json.loads(a.case)
        row = (time_layer(*args, device, a.reps) if kind == "layer"
               else time_unet(*args, device, a.reps))
        print(json.dumps(row))
        return 0
    a.out.mkdir(parents=True, exist_ok=True)
    env = {
        "python": platform.python_version(), "torch": torch.__version__,
        "torchvision": torchvision.__version__, "device": a.device,
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "cudnn": torch.backends.cudnn.version() if device.type == "cuda" else None,
        "cpu_threads": torch.get_num_threads(),
    }
    print(json.dumps(env))
    report = {"environment": env}
    status = 0
    if not a.no_tests:
        report["tests"] = run_tests(a.out)
        status = report["tests"]["exit_status"]
        print(json.dumps(report["tests"]))

    if a.small:
        layer_shapes, batch, base = [(3, 4, 32, 36), (8, 8, 16, 18)], 2, 4
        unet_sizes = [(64, 72)]
    else:
        layer_shapes, batch, base = classic_layers(960, 1088), 8, 64
        unet_sizes = [(960, 1088), (480, 544), (128, 144)]
    common = ["--out", str(a.out), "--device", a.device, "--reps", str(a.reps)]
    report["layers"] = []
    for cin, cout, h, w in layer_shapes:
        row = one_case(["layer", cin, cout, h, w, batch], common)
        report["layers"].append(row)
        if "error" in row:
            print(f"{row['layer']:>22} B{batch}  failed: {row['error']}", flush=True)
            continue
        print(f"{row['layer']:>22} B{batch}  fwd {row['forward_ratio']:5.2f}x  "
              f"f+b {row['forward_backward_ratio']:5.2f}x  "
              f"(conv2d {row['forward_s']['conv2d'] * 1e3:.2f} / "
              f"{row['forward_backward_s']['conv2d'] * 1e3:.2f} ms)", flush=True)
    report["unet"] = []
    for h, w in unet_sizes:
        row = one_case(["unet", h, w, batch, base], common)
        report["unet"].append(row)
        if "error" in row:
            print(f"U-Net base {base} {h}x{w} B{batch}: failed: {row['error']}", flush=True)
            continue
        mem = f"  peak mem {row['peak_ratio']:.2f}x" if "peak_ratio" in row else ""
        print(f"U-Net base {base} {h}x{w} B{batch} train step: standard "
              f"{row['step_s']['standard'] * 1e3:.1f} ms, calibrated "
              f"{row['step_s']['calibrated'] * 1e3:.1f} ms ({row['ratio']:.2f}x){mem}", flush=True)

    tmp = a.out / "cuda-check.json.tmp"
    tmp.write_text(json.dumps(report, indent=1) + "\n")
    os.replace(tmp, a.out / "cuda-check.json")
    return status


if __name__ == "__main__":
    sys.exit(main())
