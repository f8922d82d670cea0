#!/usr/bin/env python3
"""Convert a PyTorch checkpoint (.pth / .pt) to safetensors + a JSON sidecar for calibconv.

    .venv/bin/python tools/convert_checkpoint.py MODEL.pth OUT.safetensors

Accepts a bare state_dict or one nested under `state_dict` / `model` / `net` (searched in that
order, recursively one level), strips DataParallel's `module.` prefix, drops non-tensor entries
(e.g. milesial/Pytorch-UNet's `mask_values`) and records them, makes every tensor contiguous in
the standard (NCHW) layout (training may leave 4-D tensors channels-last; safetensors stores
dense row-major data) and converts floating tensors to float32. The sidecar `OUT.json` records the
source file and its SHA-256, the key mapping (source key -> written key), every tensor's source
dtype and shape, the dropped entries (and those beside a nested state_dict), and the detected
architecture (milesial U-Net transposed / bilinear with its input channels, classes, base width
and depth), which `calibconv` checks before loading.
"""

import argparse
import hashlib
import json
import os
import sys
import tempfile

import torch
from safetensors.torch import save_file

NESTING_KEYS = ("state_dict", "model", "net")
PREFIXES = ("module.",)


def find_state_dict(obj, path="<root>"):
    """The dict of tensors inside `obj`, and where it was found."""
    if isinstance(obj, dict):
        if any(isinstance(v, torch.Tensor) for v in obj.values()):
            return obj, path
        for key in NESTING_KEYS:
            if key in obj:
                found = find_state_dict(obj[key], f"{path}.{key}")
                if found is not None:
                    return found
    if isinstance(obj, torch.nn.Module):
        return obj.state_dict(), f"{path} (nn.Module)"
    return None


def strip_prefix(key):
    for p in PREFIXES:
        if key.startswith(p):
            return key[len(p):]
    return key


def detect_architecture(tensors):
    """Recognise milesial/Pytorch-UNet by its keys; `None` for anything else.

    The depth is the number of `downK` blocks (4 in the public network), the base width the
    output channels of `inc`, the variant `transposed` if `up1.up.weight` exists (bilinear
    up-sampling has no parameters).
    """
    inc = tensors.get("inc.double_conv.0.weight")
    outc = tensors.get("outc.conv.weight")
    if inc is None or outc is None or "down1.maxpool_conv.1.double_conv.0.weight" not in tensors:
        return None
    depth = 0
    while f"down{depth + 1}.maxpool_conv.1.double_conv.0.weight" in tensors:
        depth += 1
    bilinear = "up1.up.weight" not in tensors
    return {
        "name": "milesial-unet",
        "variant": "bilinear" if bilinear else "transposed",
        "in_channels": int(inc.shape[1]),
        "classes": int(outc.shape[0]),
        "base": int(inc.shape[0]),
        "depth": depth,
    }


def convert(src, dst):
    with open(src, "rb") as f:
        digest = hashlib.sha256(f.read()).hexdigest()
    obj = torch.load(src, map_location="cpu", weights_only=True)
    found = find_state_dict(obj)
    if found is None:
        raise SystemExit(f"{src}: no state_dict found (looked for a dict of tensors at the root "
                         f"and under {', '.join(NESTING_KEYS)})")
    state, where = found
    tensors, mapping, dropped, dtypes = {}, {}, [], {}
    for key, value in state.items():
        if not isinstance(value, torch.Tensor):
            dropped.append({"key": key, "type": type(value).__name__})
            continue
        out_key = strip_prefix(key)
        if out_key in tensors:
            raise SystemExit(f"{src}: keys `{key}` and another both map to `{out_key}`")
        t = value.detach().cpu()
        dtypes[out_key] = {"dtype": str(t.dtype).replace("torch.", ""), "shape": list(t.shape)}
        if t.is_floating_point():
            t = t.to(torch.float32)
        # contiguous_format: standard row-major strides even for channels-last tensors.
        tensors[out_key] = t.contiguous(memory_format=torch.contiguous_format).clone()
        mapping[key] = out_key
    arch = detect_architecture(tensors)
    # Entries beside a nested state_dict (epoch, optimizer, mask_values, ...): named, not kept.
    outside = ([{"key": str(k), "type": type(v).__name__} for k, v in obj.items()
                if v is not state and not (isinstance(v, dict) and k in NESTING_KEYS)]
               if isinstance(obj, dict) and obj is not state else [])
    sidecar = {
        "source": os.path.abspath(src),
        "source_sha256": digest,
        "state_dict_at": where,
        "architecture": arch,
        "key_mapping": mapping,
        "tensors": dtypes,
        "dropped": dropped,
        "outside_state_dict": outside,
        "converter": "calibconv tools/convert_checkpoint.py 1",
    }
    # Atomic writes: temporary files in the destination folder, then rename.
    out_dir = os.path.dirname(os.path.abspath(dst))
    os.makedirs(out_dir, exist_ok=True)
    meta = {"format": "pt", "source_sha256": digest,
            "architecture": json.dumps(arch) if arch else "unknown"}
    fd, tmp = tempfile.mkstemp(dir=out_dir, suffix=".tmp")
    os.close(fd)
    save_file(tensors, tmp, metadata=meta)
    os.replace(tmp, dst)
    side = os.path.splitext(dst)[0] + ".json"
    fd, tmp = tempfile.mkstemp(dir=out_dir, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(sidecar, f, indent=2)
    os.replace(tmp, side)
    return sidecar, side


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", help=".pth/.pt file")
    ap.add_argument("out", help="output .safetensors (a .json sidecar is written next to it)")
    args = ap.parse_args()
    sidecar, side = convert(args.checkpoint, args.out)
    arch = sidecar["architecture"]
    print(f"{args.out}: {len(sidecar['tensors'])} tensors from {sidecar['state_dict_at']}, "
          f"dropped {[d['key'] for d in sidecar['dropped']]}, architecture "
          f"{arch['name'] + ' ' + arch['variant'] if arch else 'unknown'}; sidecar {side}")


if __name__ == "__main__":
    sys.exit(main())
