"""What a scene asks of a model, measured from the training frames alone: depth range, view overlap, pixel footprint.

Only training scenes' training frames are read (never held-out frames or unseen scenes, which evaluate the result).
Depth maps give the range rays must cover; reprojecting a target's depth into its nearest source views gives how many
of them see each of its pixels; the depth over the focal length gives how large a pixel is on the surfaces.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Sequence

import torch
from torch import Tensor

from gpnerf_core.data.frames import FrameCache, choose_sources
from gpnerf_core.geometry.projection import project_points
from gpnerf_core.geometry.rays import pixel_grid, rays_through_pixels
from gpnerf_core.data.dataset import SceneDataset
from gpnerf_core.interfaces import ViewSelector

MIN_VALID_DEPTH = 0.05
"""Fraction of a frame's pixels that must carry a depth for the dataset to count as having depth maps."""
OCCLUSION_TOLERANCE = 0.05
"""A reprojected point is seen by a source when its depth there is within this fraction of the source's depth map."""


@dataclass(frozen=True)
class SceneMeasurement:
    """The training scenes' needs.

    Attributes:
        scenes: the scenes measured; frames: how many training frames were read.
        has_depth: whether the frames carry depth maps (else the depth fields are None and bounds stay as set).
        depth_low, depth_median, depth_high: percentiles ``percentiles`` of the valid depth, metres.
        near, far: suggested ray bounds: the low and high percentiles widened by ``margin`` (a fraction).
        metres_per_pixel: the footprint of one pixel at the median depth (median depth / focal length), metres.
        coverage: for V = 1..max_views nearest sources, the mean fraction of a target's pixels (with depth) that at
            least 1 and at least 2 of them see: ``{V: {"1": f, "2": f}}``.
    """

    scenes: list[str]
    frames: int
    has_depth: bool
    percentiles: tuple[float, float]
    margin: float
    depth_low: float | None
    depth_median: float | None
    depth_high: float | None
    near: float | None
    far: float | None
    metres_per_pixel: float | None
    focal_px: float
    coverage: dict[int, dict[str, float]]

    def to_json(self) -> dict[str, Any]:
        data = asdict(self)
        data["coverage"] = {str(v): c for v, c in self.coverage.items()}
        return data

    def fewest_views(self, min_coverage: float) -> int | None:
        """The fewest sources whose 2-view coverage reaches ``min_coverage``; None when no V measured does."""
        for views in sorted(self.coverage):
            if self.coverage[views]["2"] >= min_coverage:
                return views
        return None


def _evenly_spaced(items: Sequence[int], count: int) -> list[int]:
    if len(items) <= count:
        return list(items)
    step = len(items) / count
    return [items[int(i * step)] for i in range(count)]


def _seen_by(depth: Tensor, intrinsics: Tensor, c2w: Tensor, sources: list[Any], stride: int) -> Tensor:
    """``[P, V]`` bool: which of the V source frames sees each target pixel with depth (in view, in front, unoccluded)."""
    height, width = depth.shape
    pixels = pixel_grid(height, width, stride)
    u, v = pixels[:, 0].long(), pixels[:, 1].long()
    z = depth[v, u]
    keep = z > 0
    pixels, z = pixels[keep], z[keep]
    if not sources:
        return torch.zeros((int(keep.sum()), 0), dtype=torch.bool)
    rays = rays_through_pixels(pixels, intrinsics, c2w, near=0.0, far=1.0)  # directions have camera z = 1
    world = rays.origins + rays.directions * z[:, None]
    uv, zs = project_points(world, torch.stack([s.intrinsics for s in sources]), torch.stack([s.c2w for s in sources]))
    inside = (zs > 1e-6) & (uv[..., 0] >= -0.5) & (uv[..., 0] <= width - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= height - 0.5)
    su = uv[..., 0].round().clamp(0, width - 1).long()
    sv = uv[..., 1].round().clamp(0, height - 1).long()
    surface = torch.stack([s.depth for s in sources])[torch.arange(len(sources))[:, None], sv, su]
    unoccluded = (surface <= 0) | (zs <= surface * (1 + OCCLUSION_TOLERANCE))
    return (inside & unoccluded).T


def measure_scenes(
    dataset: SceneDataset,
    selector: ViewSelector,
    *,
    scenes: Sequence[str],
    max_views: int,
    frames_per_scene: int = 12,
    percentiles: tuple[float, float] = (0.5, 99.5),
    margin: float = 0.2,
    stride: int = 4,
) -> SceneMeasurement:
    """Measure ``scenes`` (training scenes) from up to ``frames_per_scene`` evenly spaced training frames each.

    Args:
        max_views: coverage is measured for 1..max_views nearest sources (the view selector's choice at evaluation);
            0: not measured (a per-scene model reads no source views).
        percentiles: low and high percentiles of the valid depth that bound the rays.
        margin: the bounds are widened by this fraction (near * (1 - margin), far * (1 + margin)).
        stride: target pixels on a grid of this stride are reprojected for the coverage.
    """
    cache = FrameCache(dataset, torch.device("cpu"))
    depths: list[Tensor] = []
    focals: list[float] = []
    seen_counts: dict[int, list[Tensor]] = {v: [] for v in range(1, max_views + 1)}
    frames_read = 0
    for name in scenes:
        scene = cache.scene(name)
        for index in _evenly_spaced(scene.train_frames, frames_per_scene):
            frame = cache.frame(scene, index)
            frames_read += 1
            focals.append(float(frame.intrinsics[0, 0] + frame.intrinsics[1, 1]) / 2)
            valid = frame.depth[(frame.depth > 0) & torch.isfinite(frame.depth)]
            if valid.numel() < MIN_VALID_DEPTH * frame.depth.numel():
                continue
            depths.append(valid[:: max(1, valid.numel() // 4096)])
            if not max_views:  # a per-scene model: no source views whose coverage matters
                continue
            order = choose_sources(selector, scene, index, max_views, None)
            sources = [cache.frame(scene, i) for i in order]
            seen = _seen_by(frame.depth, frame.intrinsics, frame.c2w, sources, stride)
            for views in seen_counts:
                counts = seen[:, :views].sum(-1)
                seen_counts[views].append(torch.stack([(counts >= 1).float().mean(), (counts >= 2).float().mean()]))
    focal = sum(focals) / max(len(focals), 1)
    if not depths:
        return SceneMeasurement(list(scenes), frames_read, False, percentiles, margin, None, None, None, None, None,
                                None, focal, {})
    values = torch.cat(depths).double()
    low, median, high = (float(torch.quantile(values, q / 100.0)) for q in (percentiles[0], 50.0, percentiles[1]))
    coverage = {
        views: {"1": round(float(torch.stack(rows)[:, 0].mean()), 4), "2": round(float(torch.stack(rows)[:, 1].mean()), 4)}
        for views, rows in seen_counts.items() if rows
    }
    return SceneMeasurement(
        scenes=list(scenes),
        frames=frames_read,
        has_depth=True,
        percentiles=percentiles,
        margin=margin,
        depth_low=round(low, 4),
        depth_median=round(median, 4),
        depth_high=round(high, 4),
        near=round(low * (1 - margin), 3),
        far=round(high * (1 + margin), 3),
        metres_per_pixel=round(median / focal, 5),
        focal_px=round(focal, 2),
        coverage=coverage,
    )
