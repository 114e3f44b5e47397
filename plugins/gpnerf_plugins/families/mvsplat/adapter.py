"""MVSplat's ``GaussianAdapter``: each source pixel's raw parameters, depth and opacity -> one 3D Gaussian in the world.

Per pixel, the raw channels are ``[offset (2), scale (3), rotation (4), colour (3 (degree + 1)^2), extras]``:

* the centre is the pixel moved by ``sigmoid(offset) - 0.5`` pixels, back-projected to its **camera depth** (MVSplat
  puts it at that value along the unit ray, while its cost volume's candidates are camera depths: here both are
  camera z, the project's convention);
* scales are ``scale_min + (scale_max - scale_min) sigmoid(raw)`` times ``depth x 0.1 (1/fx + 1/fy)`` (MVSplat's
  ``get_scale_multiplier``: 0.1 of a pixel's footprint per unit), along the source camera's axes;
* the rotation is the normalised quaternion in the source camera's frame, turned into the world by its pose;
* the colour is spherical harmonics in the source camera's frame, degree ``l`` damped by ``0.1 x 0.25^l`` (MVSplat's
  ``sh_mask``); it is evaluated in that frame (``PixelGaussians.colours``), which equals rotating the harmonics into
  the world as MVSplat's ``rotate_sh`` does.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from gpnerf_core import SourceViews, quaternion_product, quaternions_of, sh_coefficients, sh_colours

GEOMETRY_CHANNELS = 9
"""Offset (2), scale (3), rotation (4)."""


@dataclass(frozen=True)
class PixelGaussians:
    """The Gaussians of V source views, one per pixel (G = V H W), view-major then row-major; what ``mvsplat`` keeps
    between renders of one source set (``SourceEncoding.SOURCE_SET``).

    Attributes:
        means: ``[G, 3]`` world, metres; scales: ``[G, 3]`` metres; rotations: ``[G, 4]`` world quaternions
            ``(w, x, y, z)``; opacities: ``[G]``.
        harmonics: ``[G, 3, (degree + 1)^2]`` colour coefficients in the source camera's frame.
        view_of: ``[G]`` int64 the source view of each Gaussian; source_rotations: ``[V, 3, 3]`` their camera-to-world
            rotations (to evaluate the colour in that frame).
        scores: ``[G, K]`` class scores (label rendering), or None.
        semantic: ``[G, C]`` the extractor's semantic feature at each Gaussian's source pixel (a head decodes them),
            or None.
        depth: ``[V, H, W]`` each source pixel's depth, metres; confidence: ``[V, H, W]`` the cost volume's peak
            probability (for pictures and the viewer).
        semantic_stride: pixels per cell of the extractor's semantic map the features came from (0: none).
        field: ``[G, C]`` a feature provider's features lifted at each Gaussian's source pixel (the feature field,
            ``+feature_provider``), or None.
    """

    means: Tensor
    scales: Tensor
    rotations: Tensor
    opacities: Tensor
    harmonics: Tensor
    view_of: Tensor
    source_rotations: Tensor
    scores: Tensor | None
    semantic: Tensor | None
    depth: Tensor
    confidence: Tensor
    semantic_stride: int = 0
    field: Tensor | None = None

    @property
    def count(self) -> int:
        return int(self.means.shape[0])

    def colours(self, camera_centre: Tensor) -> Tensor:
        """``[G, 3]`` colours seen from a camera at ``camera_centre`` ``[3]`` (world, metres)."""
        directions = self.means - camera_centre.to(self.means.dtype)
        views = self.source_rotations.shape[0]  # the Gaussians are view-major: one rotation per block
        in_source = torch.bmm(directions.reshape(views, -1, 3), self.source_rotations).reshape(-1, 3)  # (R^T d)^T
        return sh_colours(self.harmonics, in_source)


def sh_damping(degree: int, like: Tensor) -> Tensor:
    """``[(degree + 1)^2]``: 1 for degree 0, ``0.1 x 0.25^l`` for the coefficients of degree ``l`` (MVSplat)."""
    mask = torch.ones(sh_coefficients(degree), dtype=like.dtype, device=like.device)
    for level in range(1, degree + 1):
        mask[level**2: (level + 1) ** 2] = 0.1 * 0.25**level
    return mask


def pixel_gaussians(raw: Tensor, depth: Tensor, opacity: Tensor, confidence: Tensor, sources: SourceViews, *,
                    sh_degree: int, scale_min: float, scale_max: float, semantic: Tensor | None = None,
                    semantic_stride: int = 0, extras: int = 0) -> PixelGaussians:
    """The Gaussians of every source pixel (the module docstring).

    Args:
        raw: ``[V, R, H, W]`` raw parameters (``GEOMETRY_CHANNELS``, colour, then ``extras`` class scores).
        depth, opacity, confidence: ``[V, H, W]``.
        semantic: ``[V, C, H, W]`` semantic features per source pixel, or None; semantic_stride: the stride of the map
            they were upsampled from.
    """
    views, channels, height, width = raw.shape
    coefficients = sh_coefficients(sh_degree)
    flat = raw.permute(0, 2, 3, 1).reshape(views, height * width, channels)
    offset, scale, rotation, colour, scores = flat.split(
        (2, 3, 4, 3 * coefficients, channels - GEOMETRY_CHANNELS - 3 * coefficients), dim=-1)
    kw = {"dtype": raw.dtype, "device": raw.device}
    rows, cols = torch.meshgrid(torch.arange(height, **kw), torch.arange(width, **kw), indexing="ij")
    pixels = torch.stack([cols, rows], dim=-1).reshape(1, -1, 2) + torch.sigmoid(offset) - 0.5  # [V, HW, 2]
    z = depth.reshape(views, -1, 1)
    rays = torch.cat([pixels, torch.ones_like(pixels[..., :1])], dim=-1) @ torch.linalg.inv(sources.intrinsics).mT
    rotation_c2w, centre = sources.c2w[:, :3, :3].to(raw.dtype), sources.c2w[:, :3, 3].to(raw.dtype)
    means = (z * rays) @ rotation_c2w.mT + centre[:, None]
    footprint = 0.1 * (1.0 / sources.intrinsics[:, 0, 0] + 1.0 / sources.intrinsics[:, 1, 1])  # [V]
    scales = (scale_min + (scale_max - scale_min) * torch.sigmoid(scale)) * z * footprint[:, None, None]
    local = rotation / (rotation.norm(dim=-1, keepdim=True) + 1e-8)
    world = quaternion_product(quaternions_of(rotation_c2w)[:, None], local)
    harmonics = colour.reshape(views, -1, 3, coefficients) * sh_damping(sh_degree, raw)
    view_of = torch.arange(views, device=raw.device).repeat_interleave(height * width)
    features = None
    if semantic is not None:
        features = semantic.permute(0, 2, 3, 1).reshape(views * height * width, -1)
    return PixelGaussians(
        means=means.reshape(-1, 3), scales=scales.reshape(-1, 3), rotations=world.reshape(-1, 4),
        opacities=opacity.reshape(-1), harmonics=harmonics.reshape(-1, 3, coefficients), view_of=view_of,
        source_rotations=rotation_c2w, scores=scores.reshape(views * height * width, -1) if extras else None,
        semantic=features, depth=depth, confidence=confidence, semantic_stride=int(semantic_stride))
