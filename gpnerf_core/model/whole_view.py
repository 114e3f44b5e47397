"""A whole view rendered ray chunk by ray chunk: what a family's ``predict`` does with its renderer (label rendering: the
per-ray scores; context-aware decoding: the rendered semantic map, decoded by a head)."""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from gpnerf_core.errors import ConfigError
from gpnerf_core.geometry.rays import pixel_grid, rays_through_pixels
from gpnerf_core.types import Prediction, RayBatch, RenderedRays, TargetCamera


def render_whole_view(camera: TargetCamera, render: Callable[[RayBatch], RenderedRays], *, stride: int,
                      chunk_rays: int, decode: Callable[[Tensor, tuple[int, int]], Tensor] | None = None) -> Prediction:
    """Render every ``stride``-th pixel of ``camera`` (cell centres), ``chunk_rays`` rays per call of ``render``.

    Args:
        render: a chunk of rays -> the pass whose outputs are the model's (its last pass): ``logits`` ``[R, K]``
            (label rendering) or ``semantic`` ``[R, C]`` (decoded), or neither.
        stride: pixels per rendered cell, already resolved by the caller (``predict``'s 0, the model's natural
            stride, is the family's to resolve; 0 here is every pixel).
        decode: the rendered semantic map ``[1, C, h, w]`` and the image size -> logits ``[1, K, H, W]`` (a head);
            None: the scores are the rendered ``logits``.

    Returns:
        colour ``[h, w, 3]`` and depth ``[h, w]`` on the stride grid; the semantic map ``[C, h, w]`` where ``decode``
        is given; the scores as ``[1, K, H, W]`` at the image's size (rendered scores repeated over each cell's
        pixels), or None when there are none.
    """
    stride = stride or 1
    height, width = camera.image_size
    if height % stride or width % stride:
        raise ConfigError(f"image size {height}x{width} is not divisible by eval.render_stride={stride}")
    pixels = pixel_grid(height, width, stride, device=camera.c2w.device)
    rays = rays_through_pixels(pixels, camera.intrinsics, camera.c2w, camera.near, camera.far)
    chunks = [render(rays.chunk(start, start + chunk_rays)) for start in range(0, rays.num_rays, chunk_rays)]
    rows, cols = height // stride, width // stride
    logits = semantic_map = None
    if decode is not None:
        semantic_map = torch.cat([chunk.semantic for chunk in chunks]).T.reshape(-1, rows, cols)
        logits = decode(semantic_map[None], (height, width))
    elif all(chunk.logits is not None for chunk in chunks):
        logits = torch.cat([chunk.logits for chunk in chunks]).T.reshape(1, -1, rows, cols)
        if stride > 1:
            logits = F.interpolate(logits, size=(height, width), mode="nearest")
    return Prediction(rgb=torch.cat([chunk.rgb for chunk in chunks]).reshape(rows, cols, 3),
                      depth=torch.cat([chunk.depth for chunk in chunks]).reshape(rows, cols), semantic=semantic_map,
                      logits=logits, stride=stride)
