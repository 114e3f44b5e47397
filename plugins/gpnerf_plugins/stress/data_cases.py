"""Stress cases on which data is evaluated: textureless surfaces and scenes never trained on."""

from __future__ import annotations

from typing import Any, Sequence

from gpnerf_core import Scene, StressCase


class Textureless(StressCase):
    """The training layouts re-rendered with one flat colour per surface (no texture to match across views)."""

    name = "textureless"
    description = "the embedded layouts re-rendered with flat colours (dataset.textureless=true), same cameras"
    axis = "textureless variant"
    levels = (1.0,)
    labels = {1.0: "flat colours"}

    def dataset_overrides(self, level: float, dataset_config: Any) -> dict[str, Any]:
        return {"textureless": True}


class UnseenScenes(StressCase):
    """Scenes never trained on (the dataset's unseen split) against the held-out views of the training scenes."""

    name = "unseen"
    description = "the dataset's unseen scenes (never trained on) instead of held-out views of training scenes"
    axis = "scenes"
    levels = (1.0,)
    labels = {1.0: "unseen scenes"}
    split = "unseen"

    def unavailable(
        self, level: float, dataset_config: Any, scenes: Sequence[Scene], num_source_views: int
    ) -> str | None:
        return None if scenes else "the dataset has no unseen scenes (dataset.unseen_scenes)"
