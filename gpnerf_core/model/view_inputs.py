"""What a model is given to render one view away from training: its source frames, their images and their encoded
maps. The one place ``render``, the viewer and ``bench`` assemble it (evaluation and ``stress`` choose per target,
``data.frames.choose_sources``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from gpnerf_core.data.frames import FrameCache, sources_at_pose
from gpnerf_core.interfaces import ViewSelector
from gpnerf_core.interfaces.model import ModelFamily
from gpnerf_core.model.feature_cache import SourceFeatureCache
from gpnerf_core.types import FeatureMaps, Scene, SourceViews


@dataclass(frozen=True)
class ViewInputs:
    """The sources of one view: frame indices, images and cameras, what the model reuses of them (its encoded maps, or
    its source set's encoding; None: ``predict`` computes it). A per-scene model (``Capabilities.generalizable`` False)
    gets none."""

    indices: tuple[int, ...] = ()
    sources: SourceViews | None = None
    features: FeatureMaps | Any | None = None


def view_inputs(
    model: ModelFamily,
    frames: FrameCache,
    selector: ViewSelector,
    scene: Scene,
    c2w: torch.Tensor,
    num_views: int,
    *,
    exclude: int | None = None,
    cache: SourceFeatureCache | None = None,
) -> ViewInputs:
    """The sources the selector picks for a camera at ``c2w`` (never frame ``exclude``), what the model reuses of them
    from ``cache`` when one is kept (``SourceFeatureCache.for_sources``); nothing for a per-scene model."""
    if not model.capabilities.generalizable:
        return ViewInputs()
    indices = sources_at_pose(selector, scene, c2w, num_views, exclude)
    sources = frames.source_views(scene, indices)
    features = None
    if cache is not None:
        features = cache.for_sources(model, scene.name, indices, sources, near=scene.near, far=scene.far)
    return ViewInputs(tuple(indices), sources, features)
