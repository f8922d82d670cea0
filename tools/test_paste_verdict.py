"""Tests of tools/paste_verdict.py (run by `make test`)."""

import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(__file__))
import paste_verdict as pv  # noqa: E402


def readme(body: str) -> str:
    return f"# T\n\n### Results\n\n{pv.BEGIN}\n{body}\n{pv.END}\n\nProse after.\n"


def test_replaces_the_block_and_demotes_headings():
    out = pv.paste(readme("old table"), "## Verdict\n\n| a |\n|---|\n")
    assert "old table" not in out
    assert f"{pv.BEGIN}\n\n#### Verdict\n\n| a |\n|---|\n\n{pv.END}" in out
    assert out.startswith("# T\n\n### Results\n") and out.endswith("Prose after.\n")


def test_missing_or_reversed_markers_are_an_error():
    with pytest.raises(ValueError, match="markers"):
        pv.paste("# no markers\n", "## V\n")
    with pytest.raises(ValueError, match="markers"):
        pv.paste(f"{pv.END}\n{pv.BEGIN}\n", "## V\n")


def test_main_writes_atomically_and_keeps_the_mode(tmp_path):
    r, v = tmp_path / "README.md", tmp_path / "verdict.md"
    r.write_text(readme("x"))
    os.chmod(r, 0o644)
    v.write_text("## New\n")
    pv.main(str(v), str(r))
    assert "#### New" in r.read_text()
    assert os.stat(r).st_mode & 0o777 == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == ["README.md", "verdict.md"]
    r.write_text("no markers\n")
    with pytest.raises(SystemExit):
        pv.main(str(v), str(r))
    assert r.read_text() == "no markers\n"
