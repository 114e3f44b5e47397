"""The fused semantic map of GP-NeRF training: rendered ray features written into the teacher map."""

from __future__ import annotations

import torch
from torch import Tensor


def cells_of_pixels(pixels: Tensor, image_size: tuple[int, int], map_size: tuple[int, int]) -> Tensor:
    """Flat cell index ``[R]`` of the map cell containing each pixel ``(u, v)`` ``[R, 2]``.

    Exact integer cells (``v // s_y``, ``u // s_x``), fixing the released code's off-by-one (REFERENCE C2).
    """
    height, width = image_size
    map_h, map_w = map_size
    col = torch.div((pixels[:, 0] + 0.5) * map_w, width, rounding_mode="floor").long().clamp(0, map_w - 1)
    row = torch.div((pixels[:, 1] + 0.5) * map_h, height, rounding_mode="floor").long().clamp(0, map_h - 1)
    return row * map_w + col


def gather_cells(feature_map: Tensor, cells: Tensor) -> Tensor:
    """Rows ``[R, C]`` of a ``[1, C, h, w]`` map at flat ``cells`` ``[R]`` (gradient preserved)."""
    return feature_map.flatten(2)[0, :, cells].T


def fuse_rendered(teacher: Tensor, rendered: Tensor, cells: Tensor) -> Tensor:
    """Replace the teacher's cells hit by rays with the rendered features (averaged where rays share a cell).

    Args:
        teacher: ``[1, C, h, w]`` target-view semantic map; keeps its gradient in the cells no ray hits.
        rendered: ``[R, C]`` rendered features; cells: ``[R]`` flat cell indices.

    Returns:
        ``[1, C, h, w]`` fused map.
    """
    _, channels, map_h, map_w = teacher.shape
    flat = teacher.flatten(2)[0]  # [C, h * w]
    sums = torch.zeros_like(flat).index_add(1, cells, rendered.T.to(flat.dtype))
    counts = torch.bincount(cells, minlength=map_h * map_w).to(flat.dtype)
    hit = counts > 0
    fused = torch.where(hit[None, :], sums / counts.clamp_min(1.0)[None, :], flat)
    return fused.reshape(1, channels, map_h, map_w)
