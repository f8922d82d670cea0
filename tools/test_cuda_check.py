"""Tests of tools/cuda_check.py (run by `make test`) on the CPU: the layer list it times and one
small run of its timings end to end (the GPU run itself is recorded in docs/bench/)."""

import json
import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import cuda_check  # noqa: E402


def test_classic_layers_are_the_distinct_3x3_layers_of_the_classic_unet():
    layers = cuda_check.classic_layers(960, 1088)
    assert layers[:2] == [(3, 64, 960, 1088), (64, 64, 960, 1088)]
    assert (512, 1024, 60, 68) in layers and (1024, 1024, 60, 68) in layers
    # Decoder: the concatenation of skip and up-sampled maps, 2c -> c, then c -> c.
    assert (1024, 512, 120, 136) in layers and (128, 64, 960, 1088) in layers
    assert layers[-1] == (128, 64, 960, 1088)  # 64 -> 64 at 960x1088 came first: deduplicated
    assert len(layers) == len(set(layers)) == 14


def test_small_cpu_run_writes_every_ratio(tmp_path):
    status = cuda_check.main(
        ["--out", str(tmp_path), "--device", "cpu", "--small", "--no-tests", "--reps", "1"]
    )
    assert status == 0
    report = json.loads((tmp_path / "cuda-check.json").read_text())
    assert report["environment"]["device"] == "cpu" and "tests" not in report
    assert [r["layer"] for r in report["layers"]] == ["3->4@32x36", "8->8@16x18"]
    for r in report["layers"]:
        assert r["forward_ratio"] > 0 and r["forward_backward_ratio"] > 0
        assert set(r["forward_s"]) == {"conv2d", "calibrated"}
    (unet,) = report["unet"]
    assert unet["input"] == "64x72" and unet["ratio"] > 0 and "peak_bytes" not in unet


def test_a_failing_case_is_recorded_with_its_exception_line(tmp_path):
    # F195 needs a map at least 4 px wide for a 3x3 kernel: the child process raises, the row
    # names the layer and the exception, and the caller goes on.
    row = cuda_check.one_case(["layer", 3, 4, 2, 3, 2],
                              ["--out", str(tmp_path), "--device", "cpu", "--reps", "1"])
    assert row["layer"] == "3->4@2x3" and row["batch"] == 2
    assert row["error"].startswith("ValueError: ") and "field of view" in row["error"]
