#!/usr/bin/env python3
"""PyTorch side of ``tests/integration/pytorch_parity.rs``: milesial/Pytorch-UNet checkpoints in,
exported state dicts out, with the reference network of ``tools/reference_unet.py`` (``torch``
only).

    .venv/bin/python tools/make_pytorch_parity.py torch-to-rust OUT_DIR
    .venv/bin/python tools/make_pytorch_parity.py classic OUT_DIR
    .venv/bin/python tools/make_pytorch_parity.py rust-to-torch STATE_DICT IO OUT

``torch-to-rust``: for each up-sampling mode (``transposed``, ``bilinear``) builds
``UNet(3, 3, bilinear, base=8)`` (depth 4, as milesial's), with random weights and BatchNorm
affine parameters *and* running statistics randomised (so eval-mode BatchNorm is not the
identity), and writes

- ``MODE.pth``: what milesial's ``train.py`` saves: ``state_dict = model.state_dict();
  state_dict['mask_values'] = [0, 1, 2]; torch.save(state_dict, path)``;
- ``MODE_nested.pth``: the same weights from a channels-last model wrapped in ``DataParallel``
  (``module.`` prefix, non-contiguous 4-D tensors), nested as ``{"model": ..., "epoch": 5}``;
- ``MODE_io.safetensors``: ``input`` [2, 3, 37, 45] (odd sizes exercise ``F.pad`` centring at
  every level) and ``output`` (``model.eval()``, raw logits);
- ``MODE_1class.pth``: a ``UNet(3, 1, bilinear, base=8)`` saved the same way, the shape of a
  calibconv depth network (initial weights of an experiment in the tests).

``classic OUT_DIR``: the same for milesial's own size, ``UNet(3, 2, bilinear)`` (base 64,
31,037,698 / 17,263,042 parameters): ``classic_MODE.pth`` and ``classic_MODE_io.safetensors``
(input [1, 3, 37, 45]).

``rust-to-torch``: builds the network the ``architecture`` metadata of STATE_DICT names, loads
STATE_DICT with ``load_state_dict(strict=True)``, runs IO's ``input`` in eval mode and writes
``output`` to OUT.
"""

import json
import sys
from pathlib import Path

import torch
import torch.nn as nn
from safetensors import safe_open
from safetensors.torch import load_file, save_file

sys.dont_write_bytecode = True  # no tools/__pycache__ in the working tree
sys.path.insert(0, str(Path(__file__).resolve().parent))
from reference_unet import UNet, randomise_batchnorm  # noqa: E402

MODES = {"transposed": False, "bilinear": True}


def random_unet(seed, classes, bilinear, input_shape, **kwargs):
    """A UNet(3, classes, bilinear, **kwargs) in eval mode with random weights and BatchNorm
    statistics (torch seed `seed`), a random input of `input_shape` and its output."""
    torch.manual_seed(seed)
    model = UNet(3, classes, bilinear=bilinear, **kwargs)
    randomise_batchnorm(model, 123)
    model.eval()
    x = torch.rand(*input_shape)
    with torch.no_grad():
        y = model(x)
    return model, x, y


def save_milesial(model, mask_values, path):
    """What milesial's train.py saves: the state_dict plus the data set's mask values."""
    state = model.state_dict()
    state["mask_values"] = mask_values
    torch.save(state, path)


def torch_to_rust(out_dir):
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for seed, (mode, bilinear) in enumerate(MODES.items()):
        model, x, y = random_unet(100 + seed, 3, bilinear, (2, 3, 37, 45), base=8)
        save_milesial(model, [0, 1, 2], out_dir / f"{mode}.pth")
        # Channels-last, DataParallel (`module.`), nested under `model`.
        wrapped = nn.DataParallel(model.to(memory_format=torch.channels_last))
        nested = wrapped.state_dict()
        w = nested["module.inc.double_conv.0.weight"]
        assert not w.is_contiguous(), "channels-last weights should not be contiguous"
        torch.save({"model": nested, "epoch": 5, "mask_values": [0, 1, 2]},
                   out_dir / f"{mode}_nested.pth")
        save_file({"input": x, "output": y.contiguous()}, out_dir / f"{mode}_io.safetensors",
                  metadata={"about": f"tools/make_pytorch_parity.py, torch {torch.__version__}"})
        one = UNet(3, 1, bilinear=bilinear, base=8)
        randomise_batchnorm(one, 123)
        save_milesial(one, [0, 1], out_dir / f"{mode}_1class.pth")
        print(f"{mode}: {len(model.state_dict())} keys, output {tuple(y.shape)}")


def classic(out_dir):
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for seed, (mode, bilinear) in enumerate(MODES.items()):
        model, x, y = random_unet(200 + seed, 2, bilinear, (1, 3, 37, 45))
        save_milesial(model, [0, 1], out_dir / f"classic_{mode}.pth")
        save_file({"input": x, "output": y.contiguous()},
                  out_dir / f"classic_{mode}_io.safetensors")
        n = sum(p.numel() for p in model.parameters())
        print(f"classic {mode}: {len(model.state_dict())} keys, {n} parameters")


def rust_to_torch(state_path, io_path, out_path):
    with safe_open(state_path, "pt") as f:
        arch = json.loads(f.metadata()["architecture"])
    if arch["depth"] != 4:
        sys.exit(f"{state_path}: depth {arch['depth']}; the reference network has depth 4")
    model = UNet(arch["in_channels"], arch["classes"], bilinear=arch["variant"] == "bilinear",
                 base=arch["base"])
    model.load_state_dict(load_file(state_path), strict=True)
    model.eval()
    x = load_file(io_path)["input"]
    with torch.no_grad():
        y = model(x)
    save_file({"output": y.contiguous()}, out_path)
    print(f"{state_path}: loaded strictly ({len(model.state_dict())} keys), output "
          f"{tuple(y.shape)}")


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "torch-to-rust":
        torch_to_rust(sys.argv[2])
    elif len(sys.argv) == 3 and sys.argv[1] == "classic":
        classic(sys.argv[2])
    elif len(sys.argv) == 5 and sys.argv[1] == "rust-to-torch":
        rust_to_torch(*sys.argv[2:])
    else:
        sys.exit(__doc__)
