"""The generic check of a dataset's files before training (``SceneDataset.check_files``).

``quick``: every scene loads (its reader indexes the files and reads the image headers and poses), every camera
pose is a finite rigid transform and the cameras' scale fits the scene's near/far (``gpnerf_core.geometry.pose_sanity``).
``full``: also every training and evaluation frame decodes, its colours lie in [0, 1], its depth is finite and
non-negative and its labels are class ids or the ignore index. ``off``: nothing.

``check_scene_files`` returns the problems that refuse training; ``pose_warnings`` the pose findings that do not (an
outlier, isolated or turned-away camera, a doubtful scale), which the pre-training check prints as notes.
"""

from __future__ import annotations

from typing import Protocol, Sequence

import torch

from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.geometry.poses import EXPECTED_RIGID, rigid_transform_problem
from gpnerf_core.geometry.pose_sanity import PoseFinding, check_poses
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
        rigid = _rigid_problems(name, scene) or _far_away_problems(name, scene)
        problems += rigid
        if not rigid:
            try:
                problems += [_located(name, f) for f in scene_pose_findings(scene) if f.refuses]
            except GpnerfError as exc:
                problems.append(f"scene {name!r} {exc}")
        if level == "full":
            for index in sorted(set(scene.train_frames) | set(scene.eval_frames)):
                problems += _frame_problems(dataset, scene, index)
    return problems


def pose_warnings(dataset: CheckedDataset, scenes: Sequence[str], level: str) -> list[str]:
    """The pose findings of ``scenes`` that do not refuse training, one line each naming the scene and frame.

    Nothing at ``level = "off"``; a scene that does not load or has a non-rigid pose is skipped (``check_scene_files``
    reports it).
    """
    if check_validation_level(level) == "off":
        return []
    notes = []
    for name in scenes:
        try:
            scene = dataset.load_scene(name)
        except GpnerfError:
            continue
        if not _rigid_problems(name, scene):
            try:
                notes += [_located(name, f) for f in scene_pose_findings(scene) if not f.refuses]
            except GpnerfError:
                continue
    return notes


def scene_pose_findings(scene: Scene) -> list[PoseFinding]:
    """Pose sanity of the frames ``scene`` uses (training and held-out), frames named by their index."""
    frames = sorted(set(scene.train_frames) | set(scene.eval_frames))
    if len(frames) < 2:
        return []
    index = torch.tensor(frames)
    return check_poses(scene.c2w[index], scene.intrinsics[index], scene.height, scene.width, scene.near, scene.far,
                       names=[str(i) for i in frames])


def _located(scene: str, finding: PoseFinding) -> str:
    where = f"scene {scene!r}" + (f" frame {finding.frame}" if finding.frame is not None else "")
    return f"{where}: {finding.message}"


def _rigid_problems(name: str, scene: Scene) -> list[str]:
    problems = []
    for index, pose in enumerate(scene.c2w):
        problem = rigid_transform_problem(pose.numpy())
        if problem is not None:
            problems.append(f"scene {name!r} frame {index}: camera pose has {problem}; expected {EXPECTED_RIGID}")
    return problems


FAR_AWAY = 1e4
"""A camera centre more than this many times ``far`` from the median centre of its scene is refused: no ray of it can
reach what the other cameras see (a pose in other units, or a corrupt value; float32 points there lose all precision)."""


def _far_away_problems(name: str, scene: Scene) -> list[str]:
    centres = scene.c2w[:, :3, 3].double()
    distances = (centres - centres.median(dim=0).values).norm(dim=-1)
    limit = FAR_AWAY * float(scene.far)
    return [f"scene {name!r} frame {index}: camera centre {float(distances[index]):.3g} m from the scene's median "
            f"centre, more than {FAR_AWAY:g} x far = {limit:.3g} m; expected poses in the units of near/far"
            for index in range(len(centres)) if float(distances[index]) > limit]


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
    elif bool((frame.depth > 0).any()) and float(frame.depth[frame.depth > 0].min()) > float(scene.far):
        problems.append(f"{where}: every known depth is beyond far={float(scene.far):g} (nearest "
                        f"{float(frame.depth[frame.depth > 0].min()):.3g}); expected depth in the units of the poses and "
                        "near/far")
    labels = frame.semantic
    bad = (labels != dataset.ignore_index) & ((labels < 0) | (labels >= dataset.num_classes))
    if bool(bad.any()):
        problems.append(
            f"{where}: label {int(labels[bad][0])} is neither a class id in [0, {dataset.num_classes}) nor the "
            f"ignore index {dataset.ignore_index}"
        )
    return problems
