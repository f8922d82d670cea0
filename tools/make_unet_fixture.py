#!/usr/bin/env python3
"""Golden U-Net fixtures from PyTorch, for ``tests/oracle_unet.rs``.

Usage (from the crate root):

    .venv/bin/python tools/make_unet_fixture.py tests/golden

The network is ``tools/reference_unet.py``: the U-Net of milesial/Pytorch-UNet as
``FORMATS.md`` describes it (module names ``inc``, ``down{k}.maxpool_conv.1``, ``up{k}.up`` /
``up{k}.conv``, ``outc.conv``; ``F.pad`` centring; ``cat([skip, up])``) with a configurable base
width. Its classic configuration (base 64, 3 inputs, 2 classes) is checked here to have
milesial's 118 / 110 state_dict keys and 31,037,698 / 17,263,042 parameters before anything is
written.

For each up-sampling mode (``transposed``, ``bilinear``) of a base-4 network (depth 4, as
milesial's) with 4 output channels, writes (deterministic, fixed seed):

- ``unet_tiny_<mode>.safetensors``: the PyTorch ``state_dict`` exactly as ``torch.save`` would
  hold it (``num_batches_tracked`` included), with BatchNorm weights, biases and running
  statistics randomised so that eval mode is not the identity;
- ``unet_tiny_<mode>_io.safetensors``: ``input`` [2, 3, 37, 69] (odd sizes exercise the
  decoder padding), ``output_eval`` (``model.eval()``, raw ``outc`` logits), ``output_train``
  (``model.train()``, batch statistics) and ``running_mean_after`` / ``running_var_after``: the
  first BatchNorm's running statistics after that one training-mode forward (momentum 0.1).
"""

import sys
from pathlib import Path

import safetensors.torch
import torch
import torch.nn as nn

# The reference network: tools/reference_unet.py (written from the public description, checked
# against the published sizes), imported rather than repeated here.
sys.dont_write_bytecode = True  # no tools/__pycache__ in the working tree
sys.path.insert(0, str(Path(__file__).resolve().parent))
from reference_unet import UNet  # noqa: E402

def check_classic():
    for bilinear, keys, params in [(False, 118, 31_037_698), (True, 110, 17_263_042)]:
        m = UNet(3, 2, bilinear=bilinear)
        n_keys = len(m.state_dict())
        n_params = sum(p.numel() for p in m.parameters())
        if (n_keys, n_params) != (keys, params):
            sys.exit(f"classic U-Net (bilinear={bilinear}): {n_keys} keys, {n_params} parameters; "
                     f"milesial/Pytorch-UNet has {keys}, {params}")


def main(out_dir):
    out_dir = Path(out_dir)
    check_classic()
    for mode in ["transposed", "bilinear"]:
        torch.manual_seed(7)
        model = UNet(3, 4, bilinear=(mode == "bilinear"), base=4)
        with torch.no_grad():
            for m in model.modules():
                if isinstance(m, nn.BatchNorm2d):
                    m.weight.uniform_(0.5, 1.5)
                    m.bias.uniform_(-0.2, 0.2)
                    m.running_mean.uniform_(-0.3, 0.3)
                    m.running_var.uniform_(0.5, 2.0)
                    m.num_batches_tracked.fill_(3)
        x = torch.rand(2, 3, 37, 69)
        state = {k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}
        with torch.no_grad():
            model.eval()
            out_eval = model(x)
            model.train()
            out_train = model(x)
        bn = model.inc.double_conv[1]
        about = (f"tools/make_unet_fixture.py, torch {torch.__version__}: milesial-layout U-Net, "
                 f"base 4, depth 4, 3 in, 4 out, {mode}")
        safetensors.torch.save_file(state, out_dir / f"unet_tiny_{mode}.safetensors",
                                    metadata={"about": about})
        io = {
            "input": x,
            "output_eval": out_eval,
            "output_train": out_train,
            "running_mean_after": bn.running_mean.detach().clone(),
            "running_var_after": bn.running_var.detach().clone(),
        }
        safetensors.torch.save_file(io, out_dir / f"unet_tiny_{mode}_io.safetensors",
                                    metadata={"about": about})
        print(f"{mode}: {len(state)} keys, output {tuple(out_eval.shape)}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "tests/golden")
