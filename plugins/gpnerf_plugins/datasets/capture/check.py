"""``data check <root> --layout capture``: every capture under ``root`` read as ``dataset=capture`` would read it."""

from __future__ import annotations

from pathlib import Path

from gpnerf_core import GpnerfError, check_scene_files
from gpnerf_plugins.datasets.capture.dataset import CaptureScenes
from gpnerf_plugins.datasets.capture.transforms import TRANSFORMS_FILE
from gpnerf_plugins.datasets.common.layout_check import LayoutReport, Problem
from gpnerf_plugins.datasets.common.pose_report import RayRange, report_poses


def check_capture_layout(root: Path, rays: RayRange | None) -> LayoutReport:
    """Parse every capture, decode every frame (``validate=full``) and check its cameras (pose sanity).

    ``rays``: the bounds pose sanity uses, or None for each capture's own (its frames' near/far or depth maps).
    """
    report = LayoutReport("capture", root)
    bounds = {"near": rays.near, "far": rays.far} if rays else {}
    try:
        dataset = CaptureScenes(root=str(root), **bounds)
        names = list(dict.fromkeys([*dataset.scenes("train"), *dataset.scenes("unseen")]))
    except GpnerfError as exc:
        report.problems.append(Problem(str(root), None, f"captures with {TRANSFORMS_FILE}", str(exc)))
        return report
    report.present["captures"] = len(names)
    report.present["labelled captures"] = 0
    report.present["frames"] = 0
    for name in names:
        where = dataset.root / TRANSFORMS_FILE if dataset.root.name == name else dataset.root / name / TRANSFORMS_FILE
        problems = check_scene_files(dataset, [name], "full")
        report.problems += [Problem(str(where), None, "a readable capture", p) for p in problems]
        if problems:
            continue
        scene = dataset.load_scene(name)
        report.present["frames"] += scene.num_frames
        report.present["labelled captures"] += int(scene.labelled)
        report_poses(report, where, list(scene.c2w.double().numpy()), scene.intrinsics.double().numpy(),
                     (scene.height, scene.width), RayRange(scene.near, scene.far),
                     [f.name for f in dataset.capture(name).frames])
    return report
