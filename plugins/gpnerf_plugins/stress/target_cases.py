"""Stress cases on which target views are scored: the held-out views near, or far from, the training cameras.

These change only the target views (``StressCase.target_frames``), so they apply to per-scene models too (which have
no source views to perturb and render only their own scene)."""

from __future__ import annotations

from typing import Any, Sequence

import torch

from gpnerf_core import Scene, StressCase


def distance_to_training(scene: Scene, frames: Sequence[int]) -> torch.Tensor:
    """``[len(frames)]``: each frame's camera centre's distance (m) to the nearest training camera centre."""
    train = scene.c2w[list(scene.train_frames), :3, 3].double()
    centres = scene.c2w[list(frames), :3, 3].double()
    return torch.cdist(centres, train).min(dim=1).values


class ViewDistance(StressCase):
    """Held-out views near, at medium distance or far from the training cameras (the model extrapolates further)."""

    name = "view_distance"
    description = ("held-out views in the nearest, middle or farthest third by distance to the nearest training camera "
                   "(per-scene models too)")
    axis = "held-out views (third by distance to the nearest training camera)"
    levels = (1.0, 2.0, 3.0)
    labels = {1.0: "near", 2.0: "medium", 3.0: "far"}
    quick_levels = (3.0,)

    def unavailable(
        self, level: float, dataset_config: Any, scenes: Sequence[Scene], num_source_views: int
    ) -> str | None:
        fewest = min((len(scene.eval_frames) for scene in scenes), default=0)
        if fewest < 3:
            return f"a scene has {fewest} held-out frame(s); three thirds by distance need 3 or more"
        return None

    def target_frames(self, level: float, scene: Scene, eval_frames: Sequence[int]) -> list[int]:
        frames = list(eval_frames)
        ranked = [frames[i] for i in torch.argsort(distance_to_training(scene, frames), stable=True).tolist()]
        third = int(level) - 1
        kept = ranked[third * len(ranked) // 3:(third + 1) * len(ranked) // 3]
        return sorted(kept)
