"""Pose sanity in a layout checker's report: what ``gpnerf_core.geometry.pose_sanity`` finds in one scene's cameras."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from gpnerf_core import GpnerfError, check_poses
from gpnerf_plugins.datasets.common.layout_check import LayoutReport, Problem


@dataclass(frozen=True)
class RayRange:
    """The ray range a layout's dataset samples by default (the ``data check`` options ``--near``/``--far``), metres."""

    near: float
    far: float


def report_poses(
    report: LayoutReport,
    where: Path,
    c2w: Sequence[np.ndarray],
    intrinsics: np.ndarray,
    size: tuple[int, int],
    bounds: RayRange,
    names: Sequence[str],
) -> None:
    """Add the pose findings of one scene to ``report``: a refusing finding (a scale that makes near/far meaningless)
    as a problem of ``where``, the others as notes naming the frame.

    Args:
        where: the scene's pose file or folder, as the report names it.
        c2w: the ``[4, 4]`` finite rigid camera-to-world poses of the frames ``names``.
        intrinsics: ``[3, 3]`` shared, or ``[N, 3, 3]``, at ``size`` = (H, W).
    """
    if len(c2w) < 2:
        return
    poses = torch.from_numpy(np.stack(c2w)).double()
    k = torch.from_numpy(np.asarray(intrinsics, dtype=np.float64))
    k = k.expand(len(c2w), 3, 3) if k.dim() == 2 else k
    try:
        findings = check_poses(poses, k, size[0], size[1], bounds.near, bounds.far, names=names)
    except GpnerfError as exc:
        report.problems.append(Problem(str(where), None, "finite cameras", str(exc)))
        return
    expected = f"cameras whose scale fits near = {bounds.near:g} m, far = {bounds.far:g} m (--near/--far)"
    for finding in findings:
        if finding.refuses:
            report.problems.append(Problem(str(where), finding.frame, expected, finding.message))
        else:
            report.notes.append(f"{where}: pose: {finding}")
