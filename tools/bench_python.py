"""Calibrated against standard models in PyTorch on the CPU: the Python package's speed.

    .venv/bin/python tools/bench_python.py [--threads 1,2] [--reps 7] [--out FILE.json]

For resnet18 (torchvision, 1000 classes; input 224x256, batch 4) and the milesial U-Net
(``tools/reference_unet.py``: base 64, transposed up-sampling, 2 classes; input 128x144, batch 8):
the standard model and a calibrated copy with the same weights (``calibrate`` with the F195
camera), timed in one process, inference (eval mode, no gradients) and a training step (train
mode: forward, cross-entropy, backward, SGD step), at each thread count. Each number is the
median of ``--reps`` repetitions after one warm-up, the two models called in turn (interleaved,
so that a change of the machine's load reaches both alike); the ratio is calibrated / standard
of the medians, with the quartiles of the paired ratios (repetition by repetition) beside it.
``--torchvision`` adds torchvision's ``deform_conv2d`` (the fallback) as a third model. The load
average (``os.getloadavg``) is recorded before and after: the ratios of interleaved runs hold
on a shared machine, the absolute times do not.
"""

from __future__ import annotations

import argparse
import copy
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import reference_unet  # noqa: E402

F195 = ROOT / "data" / "cameras" / "f195.toml"
#: (name, builder, input (H, W), batch, classes)
MODELS = [
    ("resnet18", lambda: torchvision.models.resnet18(num_classes=1000), (224, 256), 4, 1000),
    ("unet", lambda: reference_unet.UNet(3, 2, bilinear=False, base=64), (128, 144), 8, 2),
]


def interleaved(fns: dict, reps: int) -> dict:
    """Seconds of each callable, called in turn ``reps`` times after one warm-up each."""
    for f in fns.values():
        f()
    times = {k: [] for k in fns}
    for _ in range(reps):
        for k, f in fns.items():
            t = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t)
    return times


def quartiles(v):
    """(first quartile, median, third quartile) of ``v``."""
    q = statistics.quantiles(v, n=4, method="inclusive") if len(v) > 1 else [v[0]] * 3
    return q[0], statistics.median(v), q[2]


def variants(build, size, with_torchvision: bool) -> dict:
    """The standard model and its calibrated copies, same weights."""
    import calibconv.torch as ct

    torch.manual_seed(0)
    std = build()
    cal = ct.calibrate(copy.deepcopy(std), F195, size)
    out = {"standard": std, "calibrated": cal}
    if with_torchvision:
        tv = copy.deepcopy(cal)
        for m in tv.modules():
            if isinstance(m, ct.CalibratedConv2d):
                m.forward = m._torchvision_forward  # torchvision's op on the CPU
        out["torchvision"] = tv
    return out


def inference(model, x):
    model.eval()

    def run():
        with torch.no_grad():
            model(x)

    return run


def training_step(model, x, y):
    model.train()
    opt = torch.optim.SGD(model.parameters(), lr=1e-4)

    def run():
        opt.zero_grad(set_to_none=True)
        out = model(x)
        nn.functional.cross_entropy(out, y).backward()
        opt.step()

    return run


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--threads", default="1,2", help="thread counts, comma-separated")
    p.add_argument("--reps", type=int, default=7, help="timed repetitions per model (median)")
    p.add_argument("--models", default="resnet18,unet")
    p.add_argument("--torchvision", action="store_true", help="also time the fallback")
    p.add_argument("--out", type=Path, help="write the results as JSON here")
    a = p.parse_args(argv)
    import calibconv.torch as ct

    if not ct.native_available():
        print(f"warning: native kernels not available: {ct._ops.fallback_reason()}",
              file=sys.stderr)
    report = {
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "native": ct.native_available(),
        "reps": a.reps,
        "load_before": os.getloadavg(),
        "rows": [],
    }
    try:
        report["cpu"] = next(l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo")
                             if l.startswith("model name"))
    except (OSError, StopIteration):
        pass
    wanted = a.models.split(",")
    for name, build, size, batch, classes in MODELS:
        if name not in wanted:
            continue
        models = variants(build, size, a.torchvision)
        torch.manual_seed(1)
        x = torch.randn(batch, 3, *size)
        y = (torch.randint(0, classes, (batch,)) if name == "resnet18"
             else torch.randint(0, classes, (batch, *size)))
        for threads in (int(t) for t in a.threads.split(",")):
            torch.set_num_threads(threads)
            for pass_name, make in [("inference", lambda m: inference(m, x)),
                                    ("training step", lambda m: training_step(m, x, y))]:
                times = interleaved({k: make(m) for k, m in models.items()}, a.reps)
                t = {k: statistics.median(v) for k, v in times.items()}
                # Paired: repetition i of each model ran back to back, under the same load.
                paired = [c / s for c, s in zip(times["calibrated"], times["standard"])]
                q1, med, q3 = quartiles(paired)
                row = {"model": name, "input": f"{size[0]}x{size[1]}", "batch": batch,
                       "pass": pass_name, "threads": threads, "median_s": t, "times_s": times,
                       "ratio": t["calibrated"] / t["standard"],
                       "paired_ratio_quartiles": [q1, med, q3]}
                if "torchvision" in t:
                    row["torchvision_ratio"] = t["torchvision"] / t["standard"]
                report["rows"].append(row)
                extra = (f"  torchvision {row['torchvision_ratio']:.2f}x"
                         if "torchvision_ratio" in row else "")
                print(f"{name:9} {pass_name:13} {threads} thread(s): standard "
                      f"{t['standard'] * 1e3:8.1f} ms  calibrated {t['calibrated'] * 1e3:8.1f} ms"
                      f"  ratio {row['ratio']:.2f} (paired {med:.2f} [{q1:.2f}-{q3:.2f}])"
                      f"{extra}", flush=True)
    report["load_after"] = os.getloadavg()
    print(f"load average before {report['load_before']}, after {report['load_after']}")
    if a.out:
        a.out.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
