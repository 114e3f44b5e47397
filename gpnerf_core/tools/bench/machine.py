"""The machine's float32 matmul peak, measured in the same run as the figures it is compared with."""

from __future__ import annotations

import time

import torch


def matmul_peak_gflops(device: torch.device, size: int | None = None, repeats: int = 5) -> float:
    """Best of ``repeats`` timed ``size x size`` float32 matmuls, in GFLOP/s (2 n^3 flops each).

    Args:
        size: matrix side; default 2048 on the CPU, 8192 on CUDA.
    """
    n = size or (8192 if device.type == "cuda" else 2048)
    a = torch.randn(n, n, device=device)
    b = torch.randn(n, n, device=device)
    best = float("inf")
    for _ in range(repeats + 1):  # the first one warms up
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        started = time.perf_counter()
        torch.mm(a, b)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        best = min(best, time.perf_counter() - started)
    return 2 * n**3 / best / 1e9
