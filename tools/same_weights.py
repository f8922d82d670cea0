#!/usr/bin/env python3
"""Whether checkpoints hold the same tensors, bit for bit: `same_weights.py DIR_A DIR_B [NAME ...]`
compares DIR_A/NAME with DIR_B/NAME for each NAME (default: last.safetensors best.safetensors),
by name, dtype, shape and bytes; the files' metadata is left out (after a resume, metadata such
as the last logging window's mean loss differs while the weights do not). Exit status 0 when
every pair matches, 1 otherwise, with the tensors that differ. Standard library only (read by
tools/slurm-test.sh and tools/disk-full-test.sh, which run outside the venv)."""

import json
import struct
import sys

DEFAULT_NAMES = ["last.safetensors", "best.safetensors"]


def tensors(path):
    """{name: (dtype, shape, bytes)} of a safetensors file."""
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        header = json.loads(f.read(n))
        data = f.read()
    header.pop("__metadata__", None)
    return {
        k: (v["dtype"], v["shape"], data[v["data_offsets"][0] : v["data_offsets"][1]])
        for k, v in header.items()
    }


def differences(a, b):
    """The names whose tensors differ (or that only one file has), sorted."""
    return sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))


def main(argv):
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    names = argv[2:] or DEFAULT_NAMES
    same = True
    for name in names:
        a, b = tensors(f"{argv[0]}/{name}"), tensors(f"{argv[1]}/{name}")
        differ = differences(a, b)
        if differ:
            same = False
            print(f"{name}: {len(differ)} of {len(a)} tensors differ: {', '.join(differ[:5])}")
        else:
            print(f"{name}: {len(a)} tensors equal")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
