"""The generic check of a dataset's files before training (``SceneDataset.check_files``).

``quick``: every scene loads (its reader indexes the files and reads the image headers and poses) and every camera
pose is a finite rigid transform. ``full``: also every training and evaluation frame decodes, its colours lie in
[0, 1], its depth is finite and non-negative and its labels are class ids or the ignore index. ``off``: nothing.
"""

from __future__ import annotations

from typing import Protocol, Sequence

import torch

from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.geometry.poses import EXPECTED_RIGID, rigid_transform_problem
from gpnerf_core.types import Scene


class CheckedDataset(Protocol):
    """What the checks read of a dataset (``SceneDataset`` has it; the checks never need more)."""

    @property
    def num_classes(self) -> int: ...

    @property
    def ignore_index(self) -> int: ...

    def load_scene(self, name: str) -> Scene: ...


VALIDATION_LEVELS = ("quick", "full", "off")


def check_validation_level(level: str) -> str:
    """``level`` if it is one of ``VALIDATION_LEVELS`` (else a ConfigError naming ``dataset.validate``)."""
    if level not in VALIDATION_LEVELS:
        raise ConfigError(f"dataset.validate={level!r}: expected one of {', '.join(VALIDATION_LEVELS)}")
    return level


def check_scene_files(dataset: CheckedDataset, scenes: Sequence[str], level: str) -> list[str]:
    """Problems in ``scenes`` at ``level``, one line each naming the file, or the scene and frame."""
    check_validation_level(level)
    if level == "off":
        return []
    problems: list[str] = []
    for name in scenes:
        try:
            scene = dataset.load_scene(name)
        except GpnerfError as exc:
            problems.append(str(exc))
            continue
        for index, pose in enumerate(scene.c2w):
            problem = rigid_transform_problem(pose.numpy())
            if problem is not None:
                problems.append(f"scene {name!r} frame {index}: camera pose has {problem}; expected {EXPECTED_RIGID}")
        if level == "full":
            for index in sorted(set(scene.train_frames) | set(scene.eval_frames)):
                problems += _frame_problems(dataset, scene, index)
    return problems


def _frame_problems(dataset: CheckedDataset, scene: Scene, index: int) -> list[str]:
    where = f"scene {scene.name!r} frame {index}"
    try:
        frame = scene.load_frame(index)
    except GpnerfError as exc:
        return [str(exc)]
    problems = []
    rgb = frame.rgb
    if not torch.isfinite(rgb).all() or rgb.min() < 0 or rgb.max() > 1:
        problems.append(f"{where}: colours outside [0, 1] or not finite; expected RGB in [0, 1]")
    if not torch.isfinite(frame.depth).all() or frame.depth.min() < 0:
        problems.append(f"{where}: depth negative or not finite; expected metres >= 0 (0 = unknown)")
    labels = frame.semantic
    bad = (labels != dataset.ignore_index) & ((labels < 0) | (labels >= dataset.num_classes))
    if bool(bad.any()):
        problems.append(
            f"{where}: label {int(labels[bad][0])} is neither a class id in [0, {dataset.num_classes}) nor the "
            f"ignore index {dataset.ignore_index}"
        )
    return problems
