"""Tests of tools/product_harness.cpp (run by `make test`): it compiles against the crate's
kernels (src/ops/native/small_kernels.h), its products match a float64 reference, and its
timing mode runs (no timing is asserted)."""

import os
import shutil
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CXX = os.environ.get("CXX", "g++")


@pytest.fixture(scope="module")
def harness(tmp_path_factory):
    if shutil.which(CXX) is None:
        pytest.skip(f"no C++ compiler ({CXX})")
    exe = tmp_path_factory.mktemp("harness") / "product_harness"
    subprocess.run(
        [CXX, "-O2", "-std=c++17", "-I", os.path.join(ROOT, "src/ops/native"),
         os.path.join(ROOT, "tools/product_harness.cpp"), "-o", str(exe)],
        check=True,
    )
    return str(exe)


def run(exe, *args):
    out = subprocess.run([exe, *args], capture_output=True, text=True)
    if out.returncode == 3:
        pytest.skip("this CPU has no few-output-channel kernels")
    return out


def test_products_match_a_float64_reference(harness):
    out = run(harness, "check")
    assert out.returncode == 0, out.stdout + out.stderr
    lines = out.stdout.splitlines()
    assert len(lines) == 8 and all(line.startswith("ok ") for line in lines), out.stdout
    # both loops of the layer: whole reductions and slabs of a large weight
    assert "slabs of 512" in out.stdout and "slabs of 144" in out.stdout


def test_time_mode_reports_the_layer(harness):
    out = run(harness, "time", "64", "64", "200")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("64->64, 200 rows in blocks of ")
    assert "GFLOP/s" in out.stdout


def test_bad_arguments_are_refused(harness):
    for args in (["time", "64", "x", "200"], ["nothing"], []):
        out = run(harness, *args)
        assert out.returncode == 2 and "usage" in out.stderr
