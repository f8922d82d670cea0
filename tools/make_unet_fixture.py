#!/usr/bin/env python3
"""Golden U-Net fixtures from PyTorch, for ``tests/oracle_unet.rs``.

Usage (from the crate root):

    .venv/bin/python tools/make_unet_fixture.py tests/golden

The network below is the U-Net of milesial/Pytorch-UNet as ``FORMATS.md`` describes it (module
names ``inc``, ``down{k}.maxpool_conv.1``, ``up{k}.up`` / ``up{k}.conv``, ``outc.conv``;
DoubleConv = Sequential(Conv3x3 no bias, BatchNorm, ReLU, Conv3x3 no bias, BatchNorm, ReLU);
``F.pad`` centring; ``cat([skip, up])``), written here with a configurable base width and depth.
Its classic configuration (base 64, depth 4, 3 inputs, 2 classes) is checked below to have
milesial's 118 / 110 state_dict keys and 31,037,698 / 17,263,042 parameters before anything is
written.

For each up-sampling mode (``transposed``, ``bilinear``) of a base-8, depth-3 network with
4 output channels, writes (deterministic, fixed seed):

- ``unet_tiny_<mode>.safetensors``: the PyTorch ``state_dict`` exactly as ``torch.save`` would
  hold it (``num_batches_tracked`` included), with BatchNorm weights, biases and running
  statistics randomised so that eval mode is not the identity;
- ``unet_tiny_<mode>_io.safetensors``: ``input`` [2, 3, 37, 45] (odd sizes exercise the
  decoder padding), ``output_eval`` (``model.eval()``, raw ``outc`` logits), ``output_train``
  (``model.train()``, batch statistics) and ``running_mean_after`` / ``running_var_after``: the
  first BatchNorm's running statistics after that one training-mode forward (momentum 0.1).
"""

import sys
from pathlib import Path

import safetensors.torch
import torch
import torch.nn as nn
import torch.nn.functional as F


class DoubleConv(nn.Module):
    def __init__(self, c_in, c_out, mid=None):
        super().__init__()
        mid = mid or c_out
        self.double_conv = nn.Sequential(
            nn.Conv2d(c_in, mid, 3, padding=1, bias=False),
            nn.BatchNorm2d(mid),
            nn.ReLU(inplace=True),
            nn.Conv2d(mid, c_out, 3, padding=1, bias=False),
            nn.BatchNorm2d(c_out),
            nn.ReLU(inplace=True),
        )

    def forward(self, x):
        return self.double_conv(x)


class Down(nn.Module):
    def __init__(self, c_in, c_out):
        super().__init__()
        self.maxpool_conv = nn.Sequential(nn.MaxPool2d(2), DoubleConv(c_in, c_out))

    def forward(self, x):
        return self.maxpool_conv(x)


class Up(nn.Module):
    def __init__(self, c_in, c_out, bilinear):
        super().__init__()
        if bilinear:
            self.up = nn.Upsample(scale_factor=2, mode="bilinear", align_corners=True)
            self.conv = DoubleConv(c_in, c_out, c_in // 2)
        else:
            self.up = nn.ConvTranspose2d(c_in, c_in // 2, kernel_size=2, stride=2)
            self.conv = DoubleConv(c_in, c_out)

    def forward(self, x1, x2):
        x1 = self.up(x1)
        dy = x2.size(2) - x1.size(2)
        dx = x2.size(3) - x1.size(3)
        x1 = F.pad(x1, [dx // 2, dx - dx // 2, dy // 2, dy - dy // 2])
        return self.conv(torch.cat([x2, x1], dim=1))


class OutConv(nn.Module):
    def __init__(self, c_in, c_out):
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, kernel_size=1)

    def forward(self, x):
        return self.conv(x)


class UNet(nn.Module):
    def __init__(self, n_channels, n_classes, bilinear, base=64, depth=4):
        super().__init__()
        f = 2 if bilinear else 1
        self.depth = depth
        self.inc = DoubleConv(n_channels, base)
        for l in range(1, depth + 1):
            c_out = (base << l) // (f if l == depth else 1)
            setattr(self, f"down{l}", Down(base << (l - 1), c_out))
        for k in range(1, depth + 1):
            l = depth - k
            c_out = (base << l) // f if l > 0 else base
            setattr(self, f"up{k}", Up(base << (l + 1), c_out, bilinear))
        self.outc = OutConv(base, n_classes)

    def forward(self, x):
        skips = [self.inc(x)]
        for l in range(1, self.depth + 1):
            skips.append(getattr(self, f"down{l}")(skips[-1]))
        x = skips.pop()
        for k in range(1, self.depth + 1):
            x = getattr(self, f"up{k}")(x, skips.pop())
        return self.outc(x)


def check_classic():
    for bilinear, keys, params in [(False, 118, 31_037_698), (True, 110, 17_263_042)]:
        m = UNet(3, 2, bilinear)
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
        model = UNet(3, 4, bilinear=(mode == "bilinear"), base=8, depth=3)
        with torch.no_grad():
            for m in model.modules():
                if isinstance(m, nn.BatchNorm2d):
                    m.weight.uniform_(0.5, 1.5)
                    m.bias.uniform_(-0.2, 0.2)
                    m.running_mean.uniform_(-0.3, 0.3)
                    m.running_var.uniform_(0.5, 2.0)
                    m.num_batches_tracked.fill_(3)
        x = torch.rand(2, 3, 37, 45)
        state = {k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}
        with torch.no_grad():
            model.eval()
            out_eval = model(x)
            model.train()
            out_train = model(x)
        bn = model.inc.double_conv[1]
        about = (f"tools/make_unet_fixture.py, torch {torch.__version__}: milesial-layout U-Net, "
                 f"base 8, depth 3, 3 in, 4 out, {mode}")
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
