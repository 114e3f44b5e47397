"""The built-in depth sources: a sweep of candidate depths along each ray, scored on the source views' features
(``cost_volume``) or on their recorded depth (``source_depth``); the scoring is ``gpnerf_core.geometry.ray_depth``'s."""

from __future__ import annotations

import math
from dataclasses import dataclass

from gpnerf_core import (
    ConfigError, DepthBelief, DepthSource, FeatureMaps, RayBatch, SourceViews, feature_cost_belief, source_depth_belief,
)


def _check_planes(name: str, planes: object) -> int:
    if isinstance(planes, bool) or not isinstance(planes, int) or planes < 2:
        raise ConfigError(f"depth_source.planes={planes!r}: expected an integer >= 2 (candidate depths per ray of "
                          f"{name})")
    return planes


def _check_views(min_views: object, least: int) -> int:
    if isinstance(min_views, bool) or not isinstance(min_views, int) or min_views < least:
        raise ConfigError(f"depth_source.min_views={min_views!r}: expected an integer >= {least}")
    return min_views


def _check_positive(key: str, value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise ConfigError(f"depth_source.{key}={value!r}: expected {what} > 0")
    return float(value)


@dataclass
class CostVolumeConfig:
    name: str = "cost_volume"
    """Registry name of this depth source."""
    planes: int = 64
    """Candidate depths per ray, uniform in 1/depth between near and far."""
    temperature: float = 0.1
    """Softmin temperature relative to the ray's cost range: a candidate as costly as the ray's median is
    ``exp(-1 / temperature)`` as likely as its best one."""
    min_views: int = 2
    """Views that must see a candidate for its cost to count (a variance needs two)."""


class CostVolumeDepth(DepthSource):
    """MVSNet's plane-sweep cost along each ray on the family's radiance features (``FeatureMaps.radiance``): the
    variance over the source views of their unit-length features at each candidate, as a softmin belief
    (``feature_cost_belief``). Training-free: it reads the extractor the family trains for rendering, so it sharpens as
    that extractor learns; ENeRF instead trains a cost-volume network for it (not here: a second network to train on
    two cores, and the sweep is meant to cost nothing beside the rendering pass)."""

    def __init__(self, planes: int = 64, temperature: float = 0.1, min_views: int = 2) -> None:
        self.planes = _check_planes("cost_volume", planes)
        self.temperature = _check_positive("temperature", temperature, "a finite temperature")
        self.min_views = _check_views(min_views, 2)

    def belief(self, rays: RayBatch, sources: SourceViews, features: FeatureMaps) -> DepthBelief:
        return feature_cost_belief(rays, sources, features.radiance, planes=self.planes, temperature=self.temperature,
                                   min_views=self.min_views)


@dataclass
class SourceDepthConfig:
    name: str = "source_depth"
    """Registry name of this depth source."""
    planes: int = 64
    """Candidate depths per ray, uniform in 1/depth between near and far."""
    tolerance: float = 0.02
    """A candidate agrees with a view's recorded depth ``d`` within ``tolerance * d`` (at least half a candidate bin)."""
    min_views: int = 1
    """Views that must have recorded a depth at a candidate for it to count."""


class RecordedDepth(DepthSource):
    """The source views' recorded depth (``SourceViews.depth``: a dataset's depth maps, 0 where unknown), swept along
    each ray (``source_depth_belief``). A dataset without depth (a capture) gives flat beliefs: the samples spread
    along every ray, so prefer ``cost_volume`` there."""

    def __init__(self, planes: int = 64, tolerance: float = 0.02, min_views: int = 1) -> None:
        self.planes = _check_planes("source_depth", planes)
        self.tolerance = _check_positive("tolerance", tolerance, "a finite fraction of the depth")
        self.min_views = _check_views(min_views, 1)

    def belief(self, rays: RayBatch, sources: SourceViews, features: FeatureMaps) -> DepthBelief:
        if sources.depth is None:
            raise ConfigError("depth_source=source_depth needs the source views' depth; the dataset loaded none")
        return source_depth_belief(rays, sources, planes=self.planes, tolerance=self.tolerance,
                                   min_views=self.min_views)
