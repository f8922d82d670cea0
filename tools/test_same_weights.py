"""Tests of tools/same_weights.py (run by `make test`)."""

import json
import os
import struct
import sys

sys.path.insert(0, os.path.dirname(__file__))
import same_weights as sw  # noqa: E402


def write(path, tensors, metadata):
    """A safetensors file of float32 tensors {name: [values]} with string metadata."""
    header, data = {"__metadata__": metadata}, b""
    for name, values in tensors.items():
        raw = struct.pack(f"<{len(values)}f", *values)
        header[name] = {
            "dtype": "F32",
            "shape": [len(values)],
            "data_offsets": [len(data), len(data) + len(raw)],
        }
        data += raw
    text = json.dumps(header).encode()
    path.write_bytes(struct.pack("<Q", len(text)) + text + data)


def test_equal_tensors_match_whatever_the_metadata(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    write(a / "last.safetensors", {"w": [1.0, 2.0], "b": [0.5]}, {"loss": "0.1"})
    write(b / "last.safetensors", {"b": [0.5], "w": [1.0, 2.0]}, {"loss": "0.2"})
    assert sw.main([str(a), str(b), "last.safetensors"]) == 0


def test_one_bit_or_a_missing_tensor_differs(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    write(a / "last.safetensors", {"w": [1.0, 2.0], "b": [0.5]}, {})
    write(b / "last.safetensors", {"w": [1.0, 2.0000002], "b": [0.5]}, {})
    assert sw.main([str(a), str(b), "last.safetensors"]) == 1
    assert "1 of 2 tensors differ: w" in capsys.readouterr().out
    write(b / "last.safetensors", {"w": [1.0, 2.0]}, {})
    assert sw.differences(
        sw.tensors(a / "last.safetensors"), sw.tensors(b / "last.safetensors")
    ) == ["b"]
