"""The reference compositor in pure torch: per tile, every listed Gaussian against every pixel, autograd end to end.

Each tile first finds, without a graph, how far down its list any pixel walks before its transmittance would fall
under 1e-4 (in chunks, stopping once every pixel has stopped), then composites only that prefix with the graph:
early termination, done densely. Same rules as the numba kernels and the official CUDA one (``projection``'s
constants); runs on any device.
"""

from __future__ import annotations

import torch
from torch import Tensor

from gpnerf_core.geometry.gaussians.binning import TileBins
from gpnerf_core.geometry.gaussians.projection import ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN

CHUNK = 512
"""Gaussians per step of the graph-free walk."""


def alphas(u: Tensor, v: Tensor, means2d: Tensor, conics: Tensor, opacities: Tensor) -> Tensor:
    """``[P, K]`` alpha of K Gaussians at P pixel centres ``(u, v)`` ``[P]``: ``min(0.99, o exp(power))``, 0 where
    skipped (``power > 0`` or alpha < 1/255)."""
    dx, dy = means2d[None, :, 0] - u[:, None], means2d[None, :, 1] - v[:, None]
    power = -0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) - conics[:, 1] * dx * dy
    alpha = torch.clamp(opacities * torch.exp(torch.clamp(power, max=0.0)), max=ALPHA_MAX)
    keep = (power <= 0) & (alpha >= ALPHA_MIN)
    return torch.where(keep, alpha, torch.zeros_like(alpha))


def _transmittance(alpha: Tensor, start: Tensor) -> Tensor:
    """``[P, K + 1]``: ``start`` ``[P]`` then ``T * (1 - alpha_k)`` multiplied in order (as the kernels multiply)."""
    return torch.cumprod(torch.cat([start[:, None], 1.0 - alpha], dim=1), dim=1)


def _walked(u: Tensor, v: Tensor, means2d: Tensor, conics: Tensor, opacities: Tensor) -> int:
    """How many Gaussians of a tile's list the furthest-walking pixel needs (the rest come after every pixel's stop)."""
    transmittance = torch.ones_like(u)
    needed = 0
    for start in range(0, means2d.shape[0], CHUNK):
        end = min(start + CHUNK, means2d.shape[0])
        chunk = _transmittance(alphas(u, v, means2d[start:end], conics[start:end], opacities[start:end]),
                               transmittance)[:, 1:]
        longest = int((chunk >= TRANSMITTANCE_MIN).sum(dim=1).max())
        needed = start + longest if longest else needed
        transmittance = chunk[:, -1]
        if longest < end - start:  # no pixel went through the whole chunk: all have stopped
            break
    return needed


def composite_torch(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, depths: Tensor,
                    bins: TileBins, height: int, width: int) -> tuple[Tensor, Tensor, Tensor]:
    """Composite front to back per tile: ``[H, W, C]`` features, ``[H, W]`` depth and ``[H, W]`` alpha (no background).

    Args: the projected ``[G, 2]`` centres, ``[G, 3]`` conics, ``[G]`` opacities, ``[G, C]`` features, ``[G]`` depths,
    and their tile lists.
    """
    channels, size = features.shape[1], bins.tile_size
    offsets = bins.offsets.tolist()
    pixels, values = [], []
    for tile in range(len(offsets) - 1):
        if offsets[tile] == offsets[tile + 1]:
            continue
        row, col = divmod(tile, bins.tiles_x)
        v, u = torch.meshgrid(torch.arange(row * size, min(row * size + size, height), device=features.device),
                              torch.arange(col * size, min(col * size + size, width), device=features.device),
                              indexing="ij")
        v, u = v.reshape(-1), u.reshape(-1)
        uf, vf = u.to(features.dtype), v.to(features.dtype)
        ids = bins.ids[offsets[tile]:offsets[tile + 1]]
        with torch.no_grad():
            ids = ids[:_walked(uf, vf, means2d[ids], conics[ids], opacities[ids])]
        alpha = alphas(uf, vf, means2d[ids], conics[ids], opacities[ids])
        with torch.no_grad():  # the pixel stops at the first Gaussian that would take T under 1e-4, excluding it
            reached = _transmittance(alpha, torch.ones_like(uf))[:, 1:] >= TRANSMITTANCE_MIN
        alpha = torch.where(reached, alpha, torch.zeros_like(alpha))
        transmittance = _transmittance(alpha, torch.ones_like(uf))
        weights = alpha * transmittance[:, :-1]
        values.append(torch.cat([weights @ features[ids], (weights @ depths[ids])[:, None], transmittance[:, -1:]], 1))
        pixels.append(v * width + u)
    image = torch.zeros(height * width, channels + 2, dtype=features.dtype, device=features.device)
    image[:, -1] = 1.0
    if values:
        image = image.index_copy(0, torch.cat(pixels), torch.cat(values))
    image = image.reshape(height, width, channels + 2)
    return image[..., :channels], image[..., channels], 1.0 - image[..., channels + 1]
