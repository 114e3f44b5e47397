"""Rays through target pixels (OpenCV camera, pixel centres at integer coordinates)."""

from __future__ import annotations

import torch
from torch import Tensor

from gpnerf_core.types import RayBatch


def pixel_grid(height: int, width: int, stride: int = 1, device: torch.device | None = None) -> Tensor:
    """Pixel coordinates ``[h * w, 2]`` as ``(u, v)`` of a stride grid, row-major.

    With ``stride`` s the grid holds the centre of every s x s cell (``s * j + (s - 1) / 2``), so a semantic
    map rendered at stride 2 lines up with feature maps at 1/2 resolution.
    """
    offset = (stride - 1) / 2.0
    vs = torch.arange(0, height - stride + 1, stride, device=device, dtype=torch.float32) + offset
    us = torch.arange(0, width - stride + 1, stride, device=device, dtype=torch.float32) + offset
    v, u = torch.meshgrid(vs, us, indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)


def rays_through_pixels(pixels: Tensor, intrinsics: Tensor, c2w: Tensor, near: float, far: float) -> RayBatch:
    """Cast rays from the camera centre through ``pixels`` ``[R, 2]``.

    Directions are ``R_c2w @ K^-1 [u, v, 1]``: their camera-z component is 1, so the ray parameter is the
    camera depth and rendered depth compares directly with depth maps.
    """
    ones = torch.ones_like(pixels[:, :1])
    homogeneous = torch.cat([pixels, ones], dim=-1)  # [R, 3]
    cam_dirs = homogeneous @ torch.linalg.inv(intrinsics).T
    directions = cam_dirs @ c2w[:3, :3].T
    origins = c2w[:3, 3].expand_as(directions)
    num = pixels.shape[0]
    near_t = torch.full((num,), float(near), dtype=pixels.dtype, device=pixels.device)
    far_t = torch.full((num,), float(far), dtype=pixels.dtype, device=pixels.device)
    return RayBatch(origins=origins, directions=directions, pixels=pixels, near=near_t, far=far_t)
