"""Speed of the Gaussian rasterizer's CPU backends: a render (no gradients), a training forward and its backward, per
Gaussian count and channels.

    python -m gpnerf_core.tools.bench.rasterizer [threads=2] [counts=12000,24000] [channels=3,32,131]
        [backends=numba,torch] [repeats=5] [size=96x128]

Random float32 Gaussians whose centres fall in the image, 2-6 m deep, 1-3 px standard deviations per axis, random
rotations, opacities uniform in [0.05, 0.95], 16 x 16 tiles. Times are medians over ``repeats`` after one warm-up (numba
compiles in it), the whole ``rasterize_gaussians`` call (projection and binning included); the backward is that of a
weighted sum of features, depth and alpha down to the Gaussians' parameters. Figures are printed, never asserted.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import torch

from gpnerf_core.geometry.gaussians import Gaussians, rasterize_gaussians

DEFAULTS = {"threads": "2", "counts": "12000,24000", "channels": "3,32,131", "backends": "numba,torch", "repeats": "5",
            "size": "96x128"}


def cpu_model() -> str:
    """The first ``model name`` of /proc/cpuinfo, or "unknown"."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return "unknown"
    return next((line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")), "unknown")


def random_view(count: int, channels: int, height: int, width: int, seed: int = 0):
    """``count`` Gaussians as the module docstring says, their camera (identity pose) and the loss weights."""
    gen = torch.Generator().manual_seed(seed)
    focal = 1.2 * width
    intrinsics = torch.tensor([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    z = 2.0 + 4.0 * torch.rand(count, generator=gen)
    u, v = torch.rand(count, generator=gen) * width - 0.5, torch.rand(count, generator=gen) * height - 0.5
    means = torch.stack([(u - intrinsics[0, 2]) / focal * z, (v - intrinsics[1, 2]) / focal * z, z], dim=-1)
    scales = (1.0 + 2.0 * torch.rand(count, 3, generator=gen)) * z[:, None] / focal
    gaussians = Gaussians(means, scales, torch.randn(count, 4, generator=gen),
                          0.05 + 0.9 * torch.rand(count, generator=gen), torch.rand(count, channels, generator=gen))
    weights = (torch.randn(height, width, channels, generator=gen), torch.randn(height, width, generator=gen))
    return gaussians, intrinsics, weights


def time_one(backend: str, count: int, channels: int, height: int, width: int,
             repeats: int) -> tuple[float, float, float]:
    """Median seconds of a forward without gradients (rendering: eval, render, view), of a forward that records them
    (training) and of that forward's backward."""
    gaussians, intrinsics, (weight_features, weight_depth) = random_view(count, channels, height, width)
    leaves = Gaussians(*(tensor.clone().requires_grad_() for tensor in (
        gaussians.means, gaussians.scales, gaussians.rotations, gaussians.opacities, gaussians.features)))

    def forward():
        return rasterize_gaussians(leaves, intrinsics=intrinsics, c2w=torch.eye(4), height=height, width=width,
                                   backend=backend)

    def step():
        out = forward()
        ((out.features * weight_features).sum() + (out.depth * weight_depth).sum() + out.alpha.sum()).backward()

    renders, forwards, steps = [], [], []
    for index in range(repeats + 1):
        started = time.perf_counter()
        with torch.no_grad():
            forward()
        rendered = time.perf_counter()
        forward()
        middle = time.perf_counter()
        step()
        ended = time.perf_counter()
        if index:  # the first is the warm-up
            renders.append(rendered - started)
            forwards.append(middle - rendered)
            steps.append(ended - middle)
    return statistics.median(renders), statistics.median(forwards), statistics.median(steps)


def main(argv: list[str] | None = None) -> int:
    options = dict(DEFAULTS)
    for argument in sys.argv[1:] if argv is None else argv:
        key, _, value = argument.partition("=")
        if key not in DEFAULTS or not value:
            print(f"unknown argument {argument!r}; known: {', '.join(f'{k}=' for k in DEFAULTS)}")
            return 2
        options[key] = value
    threads = int(options["threads"])
    torch.set_num_threads(threads)  # numba follows torch's thread count
    height, width = (int(side) for side in options["size"].split("x"))
    print(f"CPU: {cpu_model()}; {threads} thread(s); torch {torch.__version__}; "
          f"image {height} x {width}, 16 x 16 tiles")
    print(f"{'backend':<8} {'Gaussians':>9} {'channels':>8} {'no-grad ms':>11} {'forward ms':>11} {'fwd+bwd ms':>11}")
    for backend in options["backends"].split(","):
        for count in (int(c) for c in options["counts"].split(",")):
            for channels in (int(c) for c in options["channels"].split(",")):
                render, forward, step = time_one(backend, count, channels, height, width, int(options["repeats"]))
                print(f"{backend:<8} {count:>9} {channels:>8} {render * 1e3:>11.1f} {forward * 1e3:>11.1f} "
                      f"{step * 1e3:>11.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
