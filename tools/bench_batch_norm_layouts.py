"""Forward + backward of torch.nn.BatchNorm2d on [8, C, H, W] float32, NCHW against channels-last.

The measurement behind NCHW_BELOW_CHANNELS in src/nn/calibrated.rs: libtorch's channels-last
batch norm with fewer than 16 channels runs several times slower at two threads than at one.
Usage: .venv/bin/python tools/bench_batch_norm_layouts.py THREADS (median of 60 calls, in ms).
"""

import sys
import time

import torch


def bench(channels: int, size: int, channels_last: bool) -> float:
    x = torch.randn(8, channels, size, size)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    x.requires_grad_(True)
    bn = torch.nn.BatchNorm2d(channels)
    g = torch.randn_like(x)
    times = []
    for _ in range(60):
        t = time.perf_counter()
        bn(x).backward(g)
        times.append(time.perf_counter() - t)
    times.sort()
    return times[len(times) // 2] * 1e3


def main() -> None:
    threads = int(sys.argv[1])
    torch.set_num_threads(threads)
    for channels, size in [(8, 64), (16, 32), (32, 16), (64, 8), (16, 128), (8, 128)]:
        nchw = bench(channels, size, False)
        cl = bench(channels, size, True)
        print(f"threads {threads} C{channels} {size}x{size}: contiguous {nchw:.3f} ms, "
              f"channels-last {cl:.3f} ms")


if __name__ == "__main__":
    main()
