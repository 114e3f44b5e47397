"""The CUDA compositor of ``gsplat`` (nerfstudio's), optional: its pixel stage on this module's projection and tiles.

``gsplat.rasterize_to_pixels`` composites the same projected centres, conics, opacities and depth-sorted tile lists
the other backends use, so culling, ``means2d`` (and its gradient) and the tiles are the same for every backend. gsplat
puts pixel centres at ``i + 0.5``, so the centres go in shifted by half a pixel (the same as shifting the principal
point). Its kernel caps alpha at 0.999 (not 0.99) and stops at ``T <= 1e-4`` (not ``<``); it computes in float32.
"""

from __future__ import annotations

import importlib.util

import torch
from torch import Tensor

from gpnerf_core.geometry.gaussians.binning import TileBins


def gsplat_available() -> bool:
    """Whether ``gsplat`` is installed (not imported here: importing it may compile its CUDA code)."""
    return importlib.util.find_spec("gsplat") is not None


def composite_gsplat(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, depths: Tensor,
                     bins: TileBins, height: int, width: int) -> tuple[Tensor, Tensor, Tensor]:
    """``torch_backend.composite_torch``'s contract on CUDA tensors, by ``gsplat.rasterize_to_pixels``."""
    from gsplat import rasterize_to_pixels

    dtype = features.dtype
    colours = torch.cat([features, depths[:, None]], dim=-1).float()
    offsets = bins.offsets[:-1].reshape(1, bins.tiles_y, bins.tiles_x).int()
    rendered, alpha = rasterize_to_pixels(
        (means2d + 0.5)[None].float(), conics[None].float(), colours[None].contiguous(), opacities[None].float(),
        width, height, bins.tile_size, offsets, bins.ids.int())
    rendered, alpha = rendered[0].to(dtype), alpha[0, ..., 0].to(dtype)
    return rendered[..., :-1], rendered[..., -1], alpha
