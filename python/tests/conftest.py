"""Shared paths and helpers for the calibconv Python tests (run from anywhere; `make test`).

The tests import the *installed* package (``.venv/bin/pip install ./python``), and compare with
the ``calibconv`` binary of this checkout (``target/release/calibconv``; ``make test`` builds it
first; ``CALIBCONV_BIN`` overrides the path).
"""

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CAMERAS = ROOT / "data" / "cameras"
GOLDEN = ROOT / "tests" / "golden"
F195 = CAMERAS / "f195.toml"


@pytest.fixture(scope="session")
def cli() -> Path:
    """The calibconv binary; a missing one fails (never skips) the tests that need it."""
    path = Path(os.environ.get("CALIBCONV_BIN", ROOT / "target" / "release" / "calibconv"))
    assert path.is_file(), f"{path} not found: run `cargo build --release` first"
    return path


def run_cli(cli: Path, *args: str) -> str:
    out = subprocess.run([str(cli), *args], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, f"calibconv {' '.join(args)} failed:\n{out.stderr}"
    return out.stdout


def max_rel(a, b) -> float:
    """max |a - b| / max |b|: the relative error of `a` against the reference `b`."""
    import numpy as np

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30))
