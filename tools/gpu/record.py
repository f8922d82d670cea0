"""The GPU check's record: reads the logs and JSON files tools/gpu/check.sh left in a folder and
prints docs/bench/gpu-h200.json's object:

{"device", "torch", "op_parity": {"forward_max_rel", "grad_max_rel"},
 "quick_profile": {"runs", "runs_complete", "wall_s"},
 "layers": [{"layer", "cudnn_ms", "calibrated_ms", "ratio_fwd", "ratio_fb"}],
 "paper_step": {"batch", "size", "standard_ms", "calibrated_ms", "standard_peak_gib",
                "calibrated_peak_gib"},
 "paper_profile_estimate_h", "parts", "failed"}

A part that did not run or failed leaves its fields null (its exit status is in "parts").

paper_profile_estimate_h: the paper profile's training steps on one GPU, from the measured
step times: per seed 2 baselines of 50 epochs and 10 fine-tunings of 20 epochs (4 of them
calibrated), 560 steps an epoch (4480 training views a set: 1400 panoramas, 80% train, 4 views
each, batch 8), 3 seeds. Validation and evaluation passes are not counted.
"""

import json
import pathlib
import re
import sys

STEPS_PER_EPOCH = 4480 // 8
SEEDS = 3
STANDARD_STEPS = 2 * 50 * STEPS_PER_EPOCH + 6 * 20 * STEPS_PER_EPOCH
CALIBRATED_STEPS = 4 * 20 * STEPS_PER_EPOCH


def read(path):
    try:
        return path.read_text()
    except OSError:
        return None


def load_json(path):
    text = read(path)
    try:
        return json.loads(text) if text else None
    except json.JSONDecodeError:
        return None


def op_parity(log):
    """The CUDA line of tests/cuda.rs's op parity test (float32)."""
    if not log:
        return None
    m = re.search(r"op parity on cuda:\d+: float32 forward_max_rel ([0-9.e+-]+), "
                  r"grad_max_rel ([0-9.e+-]+)", log)
    if not m:
        return None
    return {"forward_max_rel": float(m.group(1)), "grad_max_rel": float(m.group(2))}


def quick_profile(out):
    log = read(out / "quick.log") or ""
    m = re.search(r"sweep of .*: (\d+) run\(s\), (\d+) ran, (\d+) skipped \(complete\), (\d+) failed", log)
    wall = read(out / "quick_wall_s.txt")
    if not m:
        return {"runs": None, "runs_complete": None, "wall_s": float(wall) if wall else None}
    runs, ran, skipped, failed = map(int, m.groups())
    return {"runs": runs, "runs_complete": runs - failed, "wall_s": float(wall) if wall else None}


def main(out):
    out = pathlib.Path(out)
    info = load_json(out / "info.json") or {}
    devices = info.get("cuda_devices") or []
    layers_doc = load_json(out / "layers.json") or {}
    step_doc = load_json(out / "step.json") or {}
    step = next(iter(step_doc.get("steps") or []), None)
    estimate = None
    if step:
        ms = SEEDS * (STANDARD_STEPS * step["standard_ms"] + CALIBRATED_STEPS * step["calibrated_ms"])
        estimate = round(ms / 3.6e6, 1)
    record = {
        "device": devices[0]["name"] if devices else None,
        "torch": info.get("libtorch_version"),
        "op_parity": op_parity(read(out / "cuda-tests.log")),
        "quick_profile": quick_profile(out),
        "layers": [
            {k: row[k] for k in ("layer", "cudnn_ms", "calibrated_ms", "ratio_fwd", "ratio_fb")}
            for row in layers_doc.get("layers") or []
        ],
        "paper_step": None if not step else {
            "batch": step["batch"], "size": step["size"],
            "standard_ms": step["standard_ms"], "calibrated_ms": step["calibrated_ms"],
            "standard_peak_gib": step["standard_peak_gib"],
            "calibrated_peak_gib": step["calibrated_peak_gib"],
        },
        "paper_profile_estimate_h": estimate,
        "parts": (read(out / "parts.txt") or "").splitlines(),
        "load": (read(out / "load.txt") or "").splitlines(),
        "failed": (layers_doc.get("failed") or []) + (step_doc.get("failed") or []),
    }
    json.dump(record, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "target/gpu/check")
