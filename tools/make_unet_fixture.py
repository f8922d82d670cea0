#!/usr/bin/env python3
"""Golden U-Net fixtures from PyTorch, for ``tests/integration/oracle_unet.rs``.

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

# The reference network: tools/reference_unet.py (written from the public description, checked
# against the published sizes), imported rather than repeated here.
sys.dont_write_bytecode = True  # no tools/__pycache__ in the working tree
sys.path.insert(0, str(Path(__file__).resolve().parent))
from reference_unet import UNet, check_published_sizes, randomise_batchnorm  # noqa: E402


def main(out_dir):
    out_dir = Path(out_dir)
    check_published_sizes()
    for mode in ["transposed", "bilinear"]:
        torch.manual_seed(7)
        model = UNet(3, 4, bilinear=(mode == "bilinear"), base=4)
        randomise_batchnorm(model, 3)
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
