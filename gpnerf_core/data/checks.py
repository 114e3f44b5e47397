"""The generic check of a dataset's files before training (``SceneDataset.check_files``), and the value checks that it
and the layout checkers of ``data check`` share (``far_away_cameras``, ``depth_problem``): one implementation, whichever
way a dataset is checked.

``quick``: every scene loads (its reader indexes the files and reads the image headers and poses), its sparse points
(``Scene.sparse_points``, a capture's ``sparse_points.ply``) read with finite coordinates, every camera
pose is a finite rigid transform, no camera centre is absurdly far from the others, the cameras' scale fits the scene's
near/far (``gpnerf_core.geometry.pose_sanity``), and ``QUICK_FRAMES`` frames per scene, spread over it, decode with
valid values (below). ``full``: every training and evaluation frame decodes with valid values: colours in [0, 1],
depth finite, non-negative and not all beyond ``far``, labels class ids or the ignore index. ``off``: nothing.

``check_scene_files`` returns the problems that refuse training; ``pose_warnings`` the pose findings that do not (an
outlier, isolated or turned-away camera, a doubtful scale), which the pre-training check prints as notes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence

import numpy as np
import torch
from torch import Tensor

from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.geometry.poses import EXPECTED_RIGID, rigid_transform_problem
from gpnerf_core.geometry.pose_sanity import PoseFinding, check_poses
from gpnerf_core.types import Scene
from gpnerf_core.runtime.finite import all_finite


class CheckedDataset(Protocol):
    """What the checks read of a dataset (``SceneDataset`` has it; the checks never need more)."""

    @property
    def num_classes(self) -> int: ...

    @property
    def ignore_index(self) -> int: ...

    def load_scene(self, name: str) -> Scene: ...


VALIDATION_LEVELS = ("quick", "full", "off")

QUICK_FRAMES = 8
"""Frames per scene that ``quick`` decodes and checks like ``full`` does (spread evenly over the frames the scene uses,
the first and last included; every held-out frame too): a badly converted scene (depth in other units or in 8 bits, labels outside the classes)
shows on every frame, and 8 decodes per scene keep ``quick`` a small part of a run's start."""


@dataclass(frozen=True)
class ValueProblem:
    """A value a check refuses: what was ``found`` and what is ``expected`` (the caller says where: file, frame)."""

    found: str
    expected: str

    def __str__(self) -> str:
        return f"{self.found}; expected {self.expected}"


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
        problems += _sparse_point_problems(name, scene)
        for index in frames_to_check(scene, level):
            problems += _frame_problems(dataset, scene, index)
    return problems


def _sparse_point_problems(name: str, scene: Scene) -> list[str]:
    """The scene's sparse points (a capture's ``sparse_points.ply``), read as a per-scene Gaussian family reads them:
    the reader's refusal naming the file, or NaN / Inf coordinates."""
    if scene.sparse_points is None:
        return []
    try:
        points = scene.sparse_points()
    except GpnerfError as exc:
        return [str(exc)]
    if not all_finite(points.xyz):
        return [f"scene {name!r}: its sparse points hold NaN or Inf coordinates; expected finite points"]
    return []


def frames_to_check(scene: Scene, level: str) -> list[int]:
    """The frames whose values ``level`` checks: every frame the scene uses (``full``), else ``QUICK_FRAMES`` of them
    spread evenly and every held-out frame (``quick``: evaluation reads each of those after training, where a bad
    value would cost the whole run)."""
    used = sorted(set(scene.train_frames) | set(scene.eval_frames))
    if level == "full" or len(used) <= QUICK_FRAMES:
        return used
    step = (len(used) - 1) / (QUICK_FRAMES - 1)
    return sorted({used[round(k * step)] for k in range(QUICK_FRAMES)} | set(scene.eval_frames))


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


def far_away_cameras(c2w: Tensor | np.ndarray | Sequence[np.ndarray], far: float) -> dict[int, ValueProblem]:
    """The cameras (by position in ``c2w``, ``[N, 4, 4]`` finite camera-to-world poses) whose centre is more than
    ``FAR_AWAY`` x ``far`` (metres) from the median centre of all of them."""
    poses = torch.as_tensor(np.asarray(c2w) if not isinstance(c2w, Tensor) else c2w).double()
    if poses.shape[0] == 0:
        return {}
    centres = poses[:, :3, 3]
    distances = (centres - centres.median(dim=0).values).norm(dim=-1)
    limit = FAR_AWAY * float(far)
    return {
        index: ValueProblem(
            f"camera centre {float(distances[index]):.3g} m from the scene's median centre, more than {FAR_AWAY:g} x "
            f"far = {limit:.3g} m",
            "poses in the units of near/far",
        )
        for index in range(len(centres))
        if float(distances[index]) > limit
    }


def _far_away_problems(name: str, scene: Scene) -> list[str]:
    found = far_away_cameras(scene.c2w, scene.far)
    return [f"scene {name!r} frame {index}: {problem}" for index, problem in found.items()]


def depth_problem(depth: Tensor | np.ndarray, far: float) -> ValueProblem | None:
    """What is wrong with a ``[H, W]`` depth map in metres (0 = unknown): a negative or non-finite value, or every
    known depth beyond ``far`` (depth in other units than the poses and near/far); None when nothing is."""
    depth = torch.as_tensor(depth)
    if not all_finite(depth) or bool((depth < 0).any()):
        return ValueProblem("depth negative or not finite", "metres >= 0 (0 = unknown)")
    known = depth[depth > 0]
    if known.numel() and float(known.min()) > float(far):
        return ValueProblem(f"every known depth is beyond far={float(far):g} (nearest {float(known.min()):.3g})",
                            "depth in the units of the poses and near/far")
    return None


def _frame_problems(dataset: CheckedDataset, scene: Scene, index: int) -> list[str]:
    where = f"scene {scene.name!r} frame {index}"
    try:
        frame = scene.load_frame(index)
    except GpnerfError as exc:
        return [str(exc)]
    problems = []
    rgb = frame.rgb
    if not all_finite(rgb) or rgb.min() < 0 or rgb.max() > 1:
        problems.append(f"{where}: colours outside [0, 1] or not finite; expected RGB in [0, 1]")
    depth = depth_problem(frame.depth, scene.far)
    if depth is not None:
        problems.append(f"{where}: {depth}")
    labels = frame.semantic
    bad = (labels != dataset.ignore_index) & ((labels < 0) | (labels >= dataset.num_classes))
    if bool(bad.any()):
        problems.append(
            f"{where}: label {int(labels[bad][0])} is neither a class id in [0, {dataset.num_classes}) nor the "
            f"ignore index {dataset.ignore_index}"
        )
    return problems
