"""The GPU check's rasterizer step: the pure-torch reference against gsplat on the GPU (numba on the CPU in a dry run),
the same random Gaussians through both, their outputs and gradients compared and each timed.

    python gpu_check/rasterizer.py <out.json>

For each Gaussian count (24k: a 96 x 128 MVSplat frame's two source views; 200k at 240 x 320): the largest absolute
difference of the composited features, depth and alpha and of the gradients of means, opacities and features (the
loss is a fixed random weighting of every output, ``gpnerf_core.tools.bench.rasterizer.random_view``), and the median
seconds of a forward without gradients and of a forward with its backward. Without gsplat on a CUDA machine the torch
backend is timed alone and the JSON says why. Figures are printed and written, never asserted.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

from gpnerf_core.geometry.gaussians import Gaussians, rasterize_gaussians
from gpnerf_core.tools.bench.rasterizer import random_view

CASES = ((24_000, 67, 96, 128), (200_000, 67, 240, 320))
"""(Gaussians, channels, height, width): 3 colour + 64 semantic channels, as ``baselines/mvsplat_unet``."""
if os.environ.get("GPU_CHECK_DRY_RUN"):
    CASES = ((2_000, 67, 32, 48),)


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run_backend(backend: str, case: tuple[int, int, int, int], device: torch.device, repeats: int = 5) -> dict:
    count, channels, height, width = case
    gaussians, intrinsics, (weight_features, weight_depth) = random_view(count, channels, height, width)
    leaves = Gaussians(*(getattr(gaussians, name).to(device).requires_grad_() for name in
                         ("means", "scales", "rotations", "opacities", "features")))
    intrinsics, c2w = intrinsics.to(device), torch.eye(4, device=device)
    weight_features, weight_depth = weight_features.to(device), weight_depth.to(device)

    def forward():
        return rasterize_gaussians(leaves, intrinsics=intrinsics, c2w=c2w, height=height, width=width, backend=backend)

    def step():
        for leaf in (leaves.means, leaves.opacities, leaves.features):
            leaf.grad = None
        out = forward()
        ((out.features * weight_features).sum() + (out.depth * weight_depth).sum() + out.alpha.sum()).backward()
        return out

    renders, steps = [], []
    for index in range(repeats + 1):  # the first is the warm-up (kernel compilation)
        _synchronize(device)
        started = time.perf_counter()
        with torch.no_grad():
            forward()
        _synchronize(device)
        middle = time.perf_counter()
        out = step()
        _synchronize(device)
        if index:
            renders.append(middle - started)
            steps.append(time.perf_counter() - middle)
    return {
        "outputs": {"features": out.features.detach().cpu(), "depth": out.depth.detach().cpu(),
                    "alpha": out.alpha.detach().cpu(), "grad_means": leaves.means.grad.cpu(),
                    "grad_opacities": leaves.opacities.grad.cpu(), "grad_features": leaves.features.grad.cpu()},
        "render_ms": round(statistics.median(renders) * 1e3, 2),
        "forward_backward_ms": round(statistics.median(steps) * 1e3, 2),
    }


def main(out: Path) -> int:
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    other = "gsplat" if device.type == "cuda" else "numba"
    report: dict = {"device": torch.cuda.get_device_name(0) if device.type == "cuda" else "cpu", "cases": []}
    try:
        if other == "gsplat":
            import gsplat  # noqa: F401
    except ImportError as error:
        report["gsplat"] = f"not installed ({error}): the torch backend is timed alone"
        other = None
    for case in CASES:
        entry: dict = {"gaussians": case[0], "channels": case[1], "size": f"{case[2]}x{case[3]}"}
        reference = run_backend("torch", case, device)
        entry["torch"] = {key: reference[key] for key in ("render_ms", "forward_backward_ms")}
        if other is not None:
            result = run_backend(other, case, device)
            entry[other] = {key: result[key] for key in ("render_ms", "forward_backward_ms")}
            entry["max_abs_difference"] = {name: float((result["outputs"][name] - value).abs().max())
                                           for name, value in reference["outputs"].items()}
        report["cases"].append(entry)
        print(json.dumps(entry), flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/gpu_check/rasterizer.json")))
