"""Tile binning: every visible Gaussian listed in each tile its footprint box touches, each list front to back.

Tiles are ``tile_size`` x ``tile_size`` pixels, row-major (tile t covers rows ``(t // tiles_x) * tile_size ...`` and
columns ``(t % tiles_x) * tile_size ...``, cut at the image's edges). A list is sorted by camera z, ties by the
Gaussian's index, so a rendering is deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from gpnerf_core.geometry.gaussians.projection import ProjectedGaussians


@dataclass(frozen=True)
class TileBins:
    """Which Gaussians each tile walks, front to back.

    Attributes:
        offsets: ``[T + 1]`` int64: tile t walks ``ids[offsets[t]:offsets[t + 1]]`` (T = tiles_y * tiles_x).
        ids: ``[N]`` int64 Gaussian indices, N intersections, tile-major then by depth then by index.
        tile_size: the tiles' side, pixels.
        tiles_x, tiles_y: tiles per row and per column.
    """

    offsets: Tensor
    ids: Tensor
    tile_size: int
    tiles_x: int
    tiles_y: int

    @property
    def count(self) -> int:
        """N, the number of (tile, Gaussian) intersections."""
        return int(self.ids.shape[0])


Fill = Callable[[Tensor, Tensor, Tensor, int, int], tuple[Tensor, Tensor]]
"""``(ids, low, high, tiles_x, tiles_y) -> (offsets, listed ids)``: lists Gaussians ``ids`` ``[n]`` (front to back)
into the tiles ``low[i] ... high[i]`` (``[n, 2]`` tile column and row, both included)."""


def fill_tiles(ids: Tensor, low: Tensor, high: Tensor, tiles_x: int, tiles_y: int) -> tuple[Tensor, Tensor]:
    """``Fill`` in torch: one (tile, Gaussian) pair per tile of each rectangle, then a stable sort by tile."""
    device = ids.device
    span = high - low + 1  # [n, 2] tiles along u and v
    counts = span[:, 0] * span[:, 1]
    owner = torch.repeat_interleave(torch.arange(ids.shape[0], device=device), counts)
    first_x, first_y, across, before = torch.stack([low[:, 0], low[:, 1], span[:, 0], torch.cumsum(counts, 0) - counts],
                                                   dim=1)[owner].unbind(1)
    local = torch.arange(owner.shape[0], device=device) - before
    tile = (first_y + local // across) * tiles_x + first_x + local % across
    order = torch.sort(tile, stable=True).indices  # by tile, keeping the depth order within each
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.long, device=device)
    offsets[1:] = torch.cumsum(torch.bincount(tile, minlength=tiles_x * tiles_y), 0)
    return offsets, ids[owner[order]]


def bin_gaussians(projected: ProjectedGaussians, height: int, width: int, tile_size: int,
                  fill: Fill = fill_tiles) -> TileBins:
    """List the visible Gaussians of ``projected`` in the ``tile_size`` tiles of a ``height`` x ``width`` image
    (``fill`` does the listing: ``fill_tiles``, or the numba backend's counting sort, which lists the same)."""
    device = projected.means2d.device
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    ids = torch.nonzero(projected.visible).squeeze(1)
    ids = ids[torch.sort(projected.depths.detach()[ids], stable=True).indices]  # front to back, ties by index
    centre, extents = projected.means2d.detach()[ids], projected.extents[ids]
    size = torch.tensor([width - 1, height - 1], dtype=centre.dtype, device=device)
    zero = torch.zeros_like(size)
    # First and last pixel centre of the box, in the image, then their tiles.
    low = torch.minimum(torch.maximum(torch.ceil(centre - extents), zero), size).long() // tile_size
    high = torch.minimum(torch.maximum(torch.floor(centre + extents), zero), size).long() // tile_size
    offsets, listed = fill(ids, low, high, tiles_x, tiles_y)
    return TileBins(offsets=offsets, ids=listed, tile_size=tile_size, tiles_x=tiles_x, tiles_y=tiles_y)
