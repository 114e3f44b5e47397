"""A cheap depth per ray before any rendering pass, from the source views alone: where the surfaces are (ENeRF's idea,
here without a learned cost volume), as a distribution over candidate depths that ``surface_depths`` turns into a few
samples around its mode, or into samples spread along the ray where it has none.

Two sources, both swept along each ray (so they work for any set of rays: a training batch's random pixels as well as
a whole view), at ``planes`` candidate depths uniform in 1/depth between the ray's near and far:

- ``feature_cost_belief``: MVSNet's plane-sweep cost, the variance over the source views that see a candidate of
  their (unit-normalised) features there; the belief is a softmin of the cost, its temperature relative to the
  ray's own cost range, so it needs no scale of the features.
- ``source_depth_belief``: the source views' depth maps (a dataset's recorded depth): a candidate is a surface where
  the views that see it recorded a surface at its depth (within ``tolerance`` of the depth, or half a candidate bin).

Where no candidate of a ray is seen by enough views, its belief is flat over the candidates, and ``surface_depths``
falls back to samples spread along the whole ray. Conventions are ``gpnerf_core.types``'s (OpenCV cameras,
camera-to-world, depth = camera z = the ray parameter, metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from gpnerf_core.geometry.plane_sweep import MIN_DEPTH, projections_in_views
from gpnerf_core.geometry.projection import sampling_layout, world_to_camera
from gpnerf_core.geometry.sampling import stratified_inverse_depths
from gpnerf_core.types import RayBatch, SourceViews


@dataclass(frozen=True)
class DepthBelief:
    """Where a ray's surface is, as a distribution over candidate depths.

    Attributes:
        depths: ``[R, D]`` ascending candidate depths, metres.
        probabilities: ``[R, D]`` non-negative, summing to 1 per ray (flat where the views tell nothing).
        evidence: ``[R]`` bool: at least one candidate was seen by enough views to be scored.
    """

    depths: Tensor
    probabilities: Tensor
    evidence: Tensor

    @property
    def expected_depth(self) -> Tensor:
        """``[R]`` the belief's mean depth, metres."""
        return (self.probabilities * self.depths).sum(dim=-1)


def candidate_depths(rays: RayBatch, planes: int) -> Tensor:
    """``[R, planes]`` depths uniform in 1/depth between each ray's near and far (the sweep's planes along the ray)."""
    if planes < 2:
        raise ValueError(f"a depth sweep needs at least 2 planes, got {planes}")
    return stratified_inverse_depths(rays, planes, perturb=False)


def _in_views(rays: RayBatch, depths: Tensor, sources: SourceViews) -> tuple[Tensor, Tensor, Tensor]:
    """The candidates' ``grid_sample`` coordinates ``[V, R * D, 2]`` in the source views, ``inside`` ``[V, R * D]``
    and their camera depths there ``[V, R * D]``.

    A ray is a line in every camera too, so its candidates' camera points are the camera's view of its origin plus
    depth times its direction: three multiply-adds per point instead of a pose transform of each world point (the
    sweep's largest cost; the same points up to float rounding)."""
    w2c = world_to_camera(sources.c2w)
    rotation, translation = w2c[:, None, :3, :3], w2c[:, None, :3, 3]  # [V, 1, 3, 3], [V, 1, 3]
    origins = (rotation @ rays.origins[None, :, :, None])[..., 0] + translation  # [V, R, 3]
    directions = (rotation @ rays.directions[None, :, :, None])[..., 0]  # [V, R, 3]
    cam = torch.addcmul(origins[:, :, None, :], depths[None, :, :, None], directions[:, :, None, :])  # [V, R, D, 3]
    cam = cam.reshape(cam.shape[0], -1, 3)
    z = cam[..., 2]
    scale = torch.where(z > MIN_DEPTH, z, torch.ones_like(z)).reciprocal()  # behind the camera: outside anyway
    focal = sources.intrinsics[:, None, [0, 1], [0, 1]]  # [V, 1, 2]
    centre = sources.intrinsics[:, None, :2, 2]
    pixels = torch.addcmul(centre, cam[..., :2] * scale[..., None], focal)
    grid, inside = projections_in_views(pixels, z, sources.image_size)
    return grid, inside, z


def _belief(depths: Tensor, logits: Tensor, scored: Tensor) -> DepthBelief:
    """Softmax of ``logits`` ``[R, D]`` over the ``scored`` candidates; flat where a ray has none."""
    evidence = scored.any(dim=-1)
    logits = logits.masked_fill(~scored, float("-inf"))
    logits = torch.where(evidence[:, None], logits, torch.zeros_like(logits))
    return DepthBelief(depths, torch.softmax(logits, dim=-1), evidence)


def feature_cost_belief(
    rays: RayBatch,
    sources: SourceViews,
    maps: Tensor,
    *,
    planes: int,
    temperature: float = 0.1,
    min_views: int = 2,
) -> DepthBelief:
    """The plane-sweep cost of ``maps`` ``[V, C, h, w]`` (features of the source views, tiling each image) along each
    ray, as a belief.

    The cost of a candidate is the variance over the views that see it of the views' features there, each feature
    vector scaled to unit length (so a brighter view is not a different surface), summed over channels; candidates seen
    by fewer than ``min_views`` views are not scored. The belief is ``softmax(-(cost - min) / (temperature * (median -
    min)))`` over the scored candidates: a candidate as costly as the ray's median is ``exp(-1 / temperature)`` as
    likely as the best one. No gradient flows (the sweep only places samples).
    """
    if not temperature > 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    with torch.no_grad():
        depths = candidate_depths(rays, planes)
        grid, inside, _ = _in_views(rays, depths, sources)
        # Streamed view by view (one [C, R * D] slice at a time): sum_c var_c = mean_v |f_v|^2 - |mean_v f_v|^2 over
        # the views that see a candidate, the variance of variance_over_views without its [V, C, R * D] temporaries.
        maps = sampling_layout(maps.detach())  # channels-last: grid_sample reads each point's channels at once
        total = torch.zeros(maps.shape[1], grid.shape[1], dtype=maps.dtype, device=maps.device)
        squares = torch.zeros(grid.shape[1], dtype=maps.dtype, device=maps.device)
        for view in range(maps.shape[0]):
            sampled = F.grid_sample(maps[view : view + 1], grid[view : view + 1, :, None, :], mode="bilinear",
                                    padding_mode="zeros", align_corners=False)[0, :, :, 0]  # [C, R * D]
            length2 = sampled.square().sum(dim=0)
            scale = length2.clamp_min(1e-24).rsqrt() * inside[view]  # unit length (F.normalize's eps), seen views only
            total.addcmul_(sampled, scale)
            squares.add_(length2 * scale.square())
        count = inside.sum(dim=0).clamp_min(1).to(total.dtype)
        cost = (squares / count - (total / count).square().sum(dim=0)).clamp_min(0).reshape(depths.shape)  # [R, D]
        scored = (inside.sum(dim=0) >= min_views).reshape(depths.shape)
        masked = cost.masked_fill(~scored, float("inf"))
        low = masked.min(dim=-1, keepdim=True).values
        median = torch.where(scored, cost, low.expand_as(cost)).median(dim=-1, keepdim=True).values
        scale = (median - low).clamp_min(1e-6) * temperature
        logits = -(cost - low.nan_to_num(posinf=0.0)) / scale
        return _belief(depths, logits, scored)


def source_depth_belief(
    rays: RayBatch,
    sources: SourceViews,
    *,
    planes: int,
    tolerance: float = 0.02,
    min_views: int = 1,
) -> DepthBelief:
    """The source views' recorded depth (``sources.depth`` ``[V, H, W]``, 0 where unknown) along each ray, as a belief.

    A candidate at camera depth ``z`` in a view that recorded depth ``d`` at its pixel (nearest pixel) agrees by
    ``exp(-((z - d) / w)^2 / 2)``, ``w = max(tolerance * d, half the candidate bin at that depth)``; its score is the
    mean agreement over the views that see it and recorded a depth there (at least ``min_views``). The belief is the
    scores normalised: one mode where the views agree on one surface, several where views see different surfaces
    (occlusion), flat where none recorded depth.

    Raises:
        ValueError: ``sources.depth`` is None (the dataset loaded no depth).
    """
    if sources.depth is None:
        raise ValueError("source_depth_belief needs the source views' depth (SourceViews.depth); none was loaded")
    with torch.no_grad():
        depths = candidate_depths(rays, planes)
        grid, inside, z = _in_views(rays, depths, sources)
        recorded = F.grid_sample(sources.depth[:, None], grid[:, :, None, :], mode="nearest", padding_mode="zeros",
                                 align_corners=False)[:, 0, :, 0]  # [V, R * D]
        valid = inside & (recorded > 0)
        # half a candidate bin at depth z (bins uniform in 1/depth): z^2 (1/near - 1/far) / (planes - 1) / 2
        # half a candidate bin over z^2, one per candidate [1, R * D], broadcast over the views
        half_bin_per_z2 = ((1.0 / rays.near - 1.0 / rays.far) / (2 * (planes - 1)))[:, None].expand_as(depths)
        width = torch.maximum(recorded * tolerance, z.square() * half_bin_per_z2.reshape(1, -1)).clamp_min_(1e-6)
        agreement = (z - recorded).div_(width).square_().mul_(-0.5).exp_().mul_(valid)
        count = valid.sum(dim=0)
        score = (agreement.sum(dim=0) / count.clamp_min(1)).reshape(depths.shape)
        scored = (count >= min_views).reshape(depths.shape) & (score > 1e-4)
        return _belief(depths, score.clamp_min(1e-12).log(), scored)
