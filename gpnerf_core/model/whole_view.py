"""A whole view rendered ray chunk by ray chunk: what a label-rendering family's ``predict`` does with its renderer."""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F

from gpnerf_core.errors import ConfigError
from gpnerf_core.geometry.rays import pixel_grid, rays_through_pixels
from gpnerf_core.types import Prediction, RayBatch, RenderedRays, TargetCamera


def render_whole_view(camera: TargetCamera, render: Callable[[RayBatch], RenderedRays], *, stride: int,
                      chunk_rays: int) -> Prediction:
    """Render every ``stride``-th pixel of ``camera`` (cell centres), ``chunk_rays`` rays per call of ``render``.

    Args:
        render: a chunk of rays -> the pass whose outputs are the model's (its last pass); ``logits`` ``[R, K]`` or None.
        stride: pixels per rendered cell (0: every pixel).

    Returns:
        colour ``[h, w, 3]`` and depth ``[h, w]`` on the stride grid; the scores as ``[1, K, H, W]`` at the image's size
        (each cell's scores repeated over its pixels), or None when ``render`` gives none.
    """
    stride = stride or 1
    height, width = camera.image_size
    if height % stride or width % stride:
        raise ConfigError(f"image size {height}x{width} is not divisible by eval.render_stride={stride}")
    pixels = pixel_grid(height, width, stride, device=camera.c2w.device)
    rays = rays_through_pixels(pixels, camera.intrinsics, camera.c2w, camera.near, camera.far)
    chunks = [render(rays.chunk(start, start + chunk_rays)) for start in range(0, rays.num_rays, chunk_rays)]
    rows, cols = height // stride, width // stride
    logits = None
    if all(chunk.logits is not None for chunk in chunks):
        logits = torch.cat([chunk.logits for chunk in chunks]).T.reshape(1, -1, rows, cols)
        if stride > 1:
            logits = F.interpolate(logits, size=(height, width), mode="nearest")
    return Prediction(rgb=torch.cat([chunk.rgb for chunk in chunks]).reshape(rows, cols, 3),
                      depth=torch.cat([chunk.depth for chunk in chunks]).reshape(rows, cols), semantic=None,
                      logits=logits, stride=stride)
