"""Stress cases on which source views a target gets and where their cameras are said to be."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Sequence

import torch
from torch import Tensor

from gpnerf_core import ChooseSources, Scene, SourceViews, StressCase


def source_candidates(scene: Scene, target: int) -> list[int]:
    """Frames a target may take as sources: the scene's training frames except the target itself."""
    return [i for i in scene.train_frames if i != target]


def fewest_candidates(scenes: Sequence[Scene]) -> int:
    """The smallest number of source candidates any evaluated target of ``scenes`` has."""
    counts = [len(source_candidates(scene, t)) for scene in scenes for t in scene.eval_frames]
    return min(counts, default=0)


class SourceViewCount(StressCase):
    """The model is given more or fewer source views than it was trained with."""

    name = "source_views"
    description = "number of source views per target: 8, 5, 3, 2, 1 (the model's selector picks them)"
    axis = "source views per target"
    levels = (8.0, 5.0, 3.0, 2.0, 1.0)
    quick_levels = (1.0,)

    def num_source_views(self, level: float, trained: int) -> int:
        return int(level)

    def unavailable(
        self, level: float, dataset_config: Any, scenes: Sequence[Scene], num_source_views: int
    ) -> str | None:
        offered = fewest_candidates(scenes)
        if offered < level:
            return f"{int(level)} source views: a target has only {offered} training frames to take them from"
        return None


class Baseline(StressCase):
    """Source views restricted to near, medium or far cameras from the target (the wide-baseline failure)."""

    name = "baseline"
    description = "source views from the nearest, middle or farthest third of the training cameras (centre distance)"
    axis = "baseline (third of cameras by distance)"
    levels = (1.0, 2.0, 3.0)
    labels = {1.0: "near", 2.0: "medium", 3.0: "far"}
    quick_levels = (3.0,)

    def unavailable(
        self, level: float, dataset_config: Any, scenes: Sequence[Scene], num_source_views: int
    ) -> str | None:
        offered = fewest_candidates(scenes)
        if offered < 3 * num_source_views:
            return (f"a target has {offered} training frames; three disjoint thirds of {num_source_views} views "
                    f"need {3 * num_source_views}")
        return None

    def source_indices(
        self, level: float, scene: Scene, target: int, num_views: int, choose: ChooseSources
    ) -> list[int]:
        candidates = source_candidates(scene, target)
        centres = scene.c2w[candidates, :3, 3]
        distance = (centres - scene.c2w[target, :3, 3]).norm(dim=-1)
        ranked = [candidates[i] for i in torch.argsort(distance, stable=True).tolist()]
        third = len(ranked) // 3
        start = {1.0: 0, 2.0: third + (third - num_views) // 2, 3.0: len(ranked) - num_views}[level]
        return ranked[start:start + num_views]


def random_rotations(count: int, degrees: float, generator: torch.Generator) -> Tensor:
    """``[count, 3, 3]`` rotations by exactly ``degrees`` about uniformly random axes."""
    axes = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angle = math.radians(degrees)
    k = torch.zeros(count, 3, 3, dtype=torch.float64)
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    k = k - k.transpose(1, 2)
    eye = torch.eye(3, dtype=torch.float64).expand(count, 3, 3)
    return eye + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def rotate_cameras(c2w: Tensor, rotations: Tensor) -> Tensor:
    """Turn each camera about its own centre: ``R' = R @ rotation`` (the centre stays)."""
    out = c2w.clone()
    out[:, :3, :3] = (c2w[:, :3, :3].double() @ rotations.to(c2w.device)).to(c2w.dtype)
    return out


class RotationNoise(StressCase):
    """Every source camera's orientation is off by a fixed angle about a random axis."""

    name = "rotation_noise"
    description = "every source camera turned about its centre by 1, 2, 5 or 10 degrees (random axes)"
    axis = "rotation error per source camera (degrees)"
    levels = (1.0, 2.0, 5.0, 10.0)
    quick_levels = (10.0,)

    def perturb_sources(self, level: float, sources: SourceViews, generator: torch.Generator) -> SourceViews:
        rotations = random_rotations(sources.num_views, level, generator)
        return replace(sources, c2w=rotate_cameras(sources.c2w, rotations))


class TranslationNoise(StressCase):
    """Every source camera's centre is off by a fixed distance in a random direction."""

    name = "translation_noise"
    description = "every source camera centre moved by 1, 3, 10 or 30 cm in a random direction"
    axis = "translation error per source camera (m)"
    levels = (0.01, 0.03, 0.1, 0.3)
    quick_levels = (0.3,)

    def perturb_sources(self, level: float, sources: SourceViews, generator: torch.Generator) -> SourceViews:
        directions = torch.randn(sources.num_views, 3, generator=generator, dtype=torch.float64)
        directions = directions / directions.norm(dim=-1, keepdim=True)
        c2w = sources.c2w.clone()
        c2w[:, :3, 3] += (level * directions).to(c2w)
        return replace(sources, c2w=c2w)


class OneWrongCamera(StressCase):
    """One source camera (the selector's first choice) grossly wrong, the others exact."""

    name = "wrong_camera"
    description = "the first source camera turned by 20, 45 or 90 degrees and moved 0.5 m; the others exact"
    axis = "rotation error of one source camera (degrees; it also moves 0.5 m)"
    levels = (20.0, 45.0, 90.0)
    quick_levels = (90.0,)
    shift_m = 0.5

    def unavailable(
        self, level: float, dataset_config: Any, scenes: Sequence[Scene], num_source_views: int
    ) -> str | None:
        return "one wrong camera among good ones needs 2 or more source views" if num_source_views < 2 else None

    def perturb_sources(self, level: float, sources: SourceViews, generator: torch.Generator) -> SourceViews:
        c2w = sources.c2w.clone()
        c2w[:1] = rotate_cameras(c2w[:1], random_rotations(1, level, generator))
        direction = torch.randn(3, generator=generator, dtype=torch.float64)
        c2w[0, :3, 3] += (self.shift_m * direction / direction.norm()).to(c2w)
        return replace(sources, c2w=c2w)
