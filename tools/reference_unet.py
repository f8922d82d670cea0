"""Reference U-Net with the architecture and state_dict names of milesial/Pytorch-UNet.

Written here from the public description (see ../shared/FORMATS.md, "milesial/Pytorch-UNet"),
with `torch` only, so that parity tests compare calibconv's Rust U-Net against an independent
PyTorch implementation:

- UNet(n_channels, n_classes, bilinear=False): inc = DoubleConv(n, 64); down1..4 = Down
  (64->128, 128->256, 256->512, 512->1024/f) with f = 2 if bilinear; up1..4 = Up(1024->512/f,
  512->256/f, 256->128/f, 128->64); outc = OutConv(64, n_classes) (1x1 conv with bias).
- DoubleConv = Sequential(Conv3x3 no bias, BatchNorm, ReLU, Conv3x3 no bias, BatchNorm, ReLU).
- Down = Sequential(MaxPool2d(2), DoubleConv) -> keys `downK.maxpool_conv.1.double_conv.*`.
- Up (transposed): `up` = ConvTranspose2d(in, in // 2, 2, stride 2), `conv` = DoubleConv(in, out);
  Up (bilinear): Upsample(x2, bilinear, align_corners=True), DoubleConv(in, out, mid=in // 2).
  The upsampled map is padded with F.pad([dx // 2, dx - dx // 2, dy // 2, dy - dy // 2]) to the
  skip's size, then cat([skip, upsampled], dim=1).

`base` scales the widths (64 in the public network) so tests can use small networks.
"""

import sys

import torch
import torch.nn as nn
import torch.nn.functional as F


class DoubleConv(nn.Module):
    def __init__(self, in_channels, out_channels, mid_channels=None):
        super().__init__()
        mid_channels = mid_channels or out_channels
        self.double_conv = nn.Sequential(
            nn.Conv2d(in_channels, mid_channels, kernel_size=3, padding=1, bias=False),
            nn.BatchNorm2d(mid_channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(mid_channels, out_channels, kernel_size=3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
        )

    def forward(self, x):
        return self.double_conv(x)


class Down(nn.Module):
    def __init__(self, in_channels, out_channels):
        super().__init__()
        self.maxpool_conv = nn.Sequential(nn.MaxPool2d(2), DoubleConv(in_channels, out_channels))

    def forward(self, x):
        return self.maxpool_conv(x)


class Up(nn.Module):
    def __init__(self, in_channels, out_channels, bilinear):
        super().__init__()
        if bilinear:
            self.up = nn.Upsample(scale_factor=2, mode="bilinear", align_corners=True)
            self.conv = DoubleConv(in_channels, out_channels, in_channels // 2)
        else:
            self.up = nn.ConvTranspose2d(in_channels, in_channels // 2, kernel_size=2, stride=2)
            self.conv = DoubleConv(in_channels, out_channels)

    def forward(self, x1, x2):
        x1 = self.up(x1)
        dy = x2.size(2) - x1.size(2)
        dx = x2.size(3) - x1.size(3)
        x1 = F.pad(x1, [dx // 2, dx - dx // 2, dy // 2, dy - dy // 2])
        return self.conv(torch.cat([x2, x1], dim=1))


class OutConv(nn.Module):
    def __init__(self, in_channels, out_channels):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size=1)

    def forward(self, x):
        return self.conv(x)


class UNet(nn.Module):
    def __init__(self, n_channels, n_classes, bilinear=False, base=64):
        super().__init__()
        self.n_channels, self.n_classes, self.bilinear = n_channels, n_classes, bilinear
        f = 2 if bilinear else 1
        b = base
        self.inc = DoubleConv(n_channels, b)
        self.down1 = Down(b, 2 * b)
        self.down2 = Down(2 * b, 4 * b)
        self.down3 = Down(4 * b, 8 * b)
        self.down4 = Down(8 * b, 16 * b // f)
        self.up1 = Up(16 * b, 8 * b // f, bilinear)
        self.up2 = Up(8 * b, 4 * b // f, bilinear)
        self.up3 = Up(4 * b, 2 * b // f, bilinear)
        self.up4 = Up(2 * b, b, bilinear)
        self.outc = OutConv(b, n_classes)

    def forward(self, x):
        x1 = self.inc(x)
        x2 = self.down1(x1)
        x3 = self.down2(x2)
        x4 = self.down3(x3)
        x5 = self.down4(x4)
        x = self.up1(x5, x4)
        x = self.up2(x, x3)
        x = self.up3(x, x2)
        x = self.up4(x, x1)
        return self.outc(x)


# The public network's published sizes (FORMATS.md): (bilinear, state_dict keys, parameters) of
# UNet(3, 2, bilinear).
PUBLISHED_SIZES = [(False, 118, 31_037_698), (True, 110, 17_263_042)]


def check_published_sizes():
    """Exits unless UNet(3, 2, bilinear) has the published key and parameter counts (a
    self-check of this description); returns [(bilinear, keys, parameters)]."""
    sizes = []
    for bilinear, keys, params in PUBLISHED_SIZES:
        net = UNet(3, 2, bilinear=bilinear)
        n_keys = len(net.state_dict())
        n_params = sum(p.numel() for p in net.parameters())
        if (n_keys, n_params) != (keys, params):
            sys.exit(f"classic U-Net (bilinear={bilinear}): {n_keys} keys, {n_params} parameters; "
                     f"milesial/Pytorch-UNet has {keys}, {params}")
        sizes.append((bilinear, n_keys, n_params))
    return sizes


def randomise_batchnorm(model, batches_tracked):
    """Random BatchNorm affine parameters and running statistics (so that eval-mode BatchNorm is
    not the identity), drawn from torch's global generator in module order."""
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.2, 0.2)
                m.running_mean.uniform_(-0.3, 0.3)
                m.running_var.uniform_(0.5, 2.0)
                m.num_batches_tracked.fill_(batches_tracked)


if __name__ == "__main__":
    for bilinear, n_keys, n_params in check_published_sizes():
        print(f"bilinear={bilinear}: {n_keys} keys, {n_params} parameters (as published)")
