"""The RPN's anchors (Ren et al. 2015; one size per FPN level, Lin et al. 2017), as torchvision's
``AnchorGenerator`` places them."""

from __future__ import annotations

import torch
from torch import Tensor


def cell_anchors(size: float, aspect_ratios: list[float]) -> Tensor:
    """``[A, 4]`` anchors centred on (0, 0) of area ``size ** 2``, one per aspect ratio (height / width), with the
    corners rounded to whole pixels (torchvision's)."""
    ratios = torch.as_tensor(aspect_ratios, dtype=torch.float32)
    h_ratio = torch.sqrt(ratios)
    w_ratio = 1.0 / h_ratio
    ws, hs = w_ratio * size, h_ratio * size
    return (torch.stack([-ws, -hs, ws, hs], dim=1) / 2).round()


def grid_anchors(size: float, aspect_ratios: list[float], grid: tuple[int, int], stride: tuple[int, int]) -> Tensor:
    """``[h * w * A, 4]`` anchors of one FPN level of ``grid = (h, w)`` cells, ``stride = (sy, sx)`` pixels apart
    (torchvision's: image size // grid size on each axis): at the top-left corner of every cell (row-major), the ``A``
    cell anchors in order, matching a head's output laid out as ``[h, w, A]``."""
    h, w = grid
    ys = torch.arange(h, dtype=torch.float32) * stride[0]
    xs = torch.arange(w, dtype=torch.float32) * stride[1]
    shift_y, shift_x = torch.meshgrid(ys, xs, indexing="ij")
    shifts = torch.stack([shift_x, shift_y, shift_x, shift_y], dim=-1).reshape(-1, 1, 4)
    return (shifts + cell_anchors(size, aspect_ratios)[None]).reshape(-1, 4)


def pyramid_anchors(sizes: list[float], aspect_ratios: list[float], grids: list[tuple[int, int]],
                    image_size: tuple[int, int]) -> list[Tensor]:
    """One ``grid_anchors`` per FPN level (``sizes[k]`` on level ``k``), finest first, for an input of ``image_size =
    (H, W)`` pixels."""
    height, width = image_size
    return [grid_anchors(s, aspect_ratios, g, (height // g[0], width // g[1])) for s, g in zip(sizes, grids)]
