"""Layout checkers behind ``python -m gpnerf_core data check <root> --layout replica|replica_instance``.

They walk every scene (and sequence), decode every file and report each problem with its file, frame, what the
layout expects and what was found, instead of stopping at the first one as the loaders do. Given the ray range, they
also report each sequence's pose findings (``gpnerf_core.geometry.pose_sanity``) with the frame numbers, and refuse what
``dataset.validate`` refuses (``gpnerf_core.data.checks``): a camera absurdly far from the others, a depth map beyond
``far`` everywhere.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from gpnerf_core import EXPECTED_RIGID, depth_problem, far_away_cameras, rigid_transform_problem
from gpnerf_plugins.datasets.common.decoding import DEPTH_UNITS_PER_METRE
from gpnerf_plugins.datasets.common.image_io import ImageError, describe, is_integer_map, is_rgb8, one_line_error, read_png
from gpnerf_plugins.datasets.common.layout_check import LayoutReport, Problem
from gpnerf_plugins.datasets.common.pose_report import RayRange, report_poses
from gpnerf_plugins.datasets.replica.classes import CLASS_NAMES, MAX_RAW_ID, raw_to_class_table
from gpnerf_plugins.datasets.replica.layout import (
    CLASS_DIR,
    DEPTH_DIR,
    INSTANCE_DIR,
    RGB_DIR,
    TRAJECTORY_FILE,
    frame_file_pattern,
    hfov_intrinsics,
)
from gpnerf_plugins.datasets.replica.splits import INSTANCE_SCENES_FILE, PROTOCOL_FILES, read_split_file

POSE_ROW = "a row of 16 numbers (row-major 4x4 camera-to-world)"


class _Walk:
    """Accumulates problems, counts, raw class-id pixel counts and instance-id counts over a whole dataset."""

    def __init__(self, report: LayoutReport, rays: RayRange | None = None, hfov_deg: float | None = None) -> None:
        self.report = report
        self.rays, self.hfov_deg = rays, hfov_deg
        self.poses: list[np.ndarray | None] = []  # the last trajectory's rows (None: unusable)
        self.counts: Counter[str] = Counter()
        self.raw_pixels = np.zeros(MAX_RAW_ID + 1, dtype=np.int64)
        self.unknown_pixels = 0
        self.labels_seen = False

    def problem(self, path: Path | str, frame: int | str | None, expected: str, found: str) -> None:
        self.report.problems.append(Problem(str(path), None if frame is None else str(frame), expected, found))

    def scan(self, folder: Path, kind: str, required: bool) -> dict[int, Path] | None:
        """``<kind>/<kind>_<i>.png`` files by number; None when the folder is absent."""
        directory = folder / kind
        if not directory.is_dir():
            if required:
                self.problem(directory, None, f"a folder of {kind}_<i>.png files", "no such folder")
            return None
        pattern = frame_file_pattern(kind)
        files: dict[int, Path] = {}
        for path in sorted(directory.iterdir()):
            match = pattern.match(path.name)
            if match is None:
                continue
            token = match.group(1)
            if not token.isdigit():
                self.problem(path, token, f"{kind}_<i>.png with an integer frame number i", f"frame name {token!r}")
            elif int(token) in files:
                self.problem(path, token, "a unique frame number", f"the same number as {files[int(token)].name}")
            else:
                files[int(token)] = path
        self.counts[kind] += len(files)
        return files

    def trajectory(self, path: Path, numbers: list[int]) -> int | None:
        """Check every pose row; returns the number of non-blank rows (None if the file is missing)."""
        if not path.is_file():
            self.problem(path, None, f"{POSE_ROW} per frame", "no such file")
            return None
        try:
            lines = path.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            self.problem(path, None, f"a text file with {POSE_ROW} per frame", one_line_error(exc))
            return None
        rows = 0
        self.poses = []
        for line_no, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            frame = numbers[rows] if rows < len(numbers) else None
            rows += 1
            self.poses.append(None)
            where = f"{path}:{line_no}"
            try:
                values = np.array([float(v) for v in line.split()], dtype=np.float64)
            except ValueError:
                self.problem(where, frame, POSE_ROW, f"non-numeric text {line.strip()[:60]!r}")
                continue
            if values.size != 16:
                self.problem(where, frame, POSE_ROW, f"{values.size} numbers")
            elif (problem := rigid_transform_problem(values.reshape(4, 4))) is not None:
                self.problem(where, frame, EXPECTED_RIGID, problem)
            else:
                self.poses[-1] = values.reshape(4, 4)
        self.counts["poses"] += rows
        return rows

    def image(self, path: Path, frame: int, kind: str, size: tuple[int, int] | None) -> np.ndarray | None:
        """Decode and check format and size (against ``size``); None if unusable."""
        try:
            image = read_png(path)
        except ImageError as exc:
            self.problem(path, frame, "a readable PNG", exc.reason)
            return None
        if not (is_rgb8(image) if kind == RGB_DIR else is_integer_map(image)):
            expected = "an 8-bit RGB or RGBA PNG" if kind == RGB_DIR else "a single-channel integer PNG"
            self.problem(path, frame, expected, describe(image))
            return None
        if kind == DEPTH_DIR and image.dtype == np.uint8:
            self.problem(path, frame, "a 16-bit depth PNG", "an 8-bit PNG (at most 0.255 m in millimetres)")
            return None
        if size is not None and image.shape[:2] != size:
            expected = f"a {size[0]}x{size[1]} (HxW) image like the rgb frames"
            self.problem(path, frame, expected, f"{image.shape[0]}x{image.shape[1]}")
            return None
        if kind == DEPTH_DIR and self.rays is not None:
            problem = depth_problem(image.astype(np.float64) / DEPTH_UNITS_PER_METRE, self.rays.far)
            if problem is not None:
                self.problem(path, frame, f"{problem.expected} (--far {self.rays.far:g})", problem.found)
        return image

    def labels(self, path: Path, frame: int, raw: np.ndarray) -> None:
        raw = raw.astype(np.int64)
        unknown = (raw < 0) | (raw > MAX_RAW_ID)
        if unknown.any():
            ids = np.unique(raw[unknown])
            shown = ", ".join(str(v) for v in ids[:5]) + (", ..." if ids.size > 5 else "")
            found = f"ids {shown} on {int(unknown.sum())} pixels"
            self.problem(path, frame, f"Replica class ids 0..{MAX_RAW_ID}", found)
            self.unknown_pixels += int(unknown.sum())
        self.raw_pixels += np.bincount(raw[~unknown], minlength=MAX_RAW_ID + 1)
        self.labels_seen = True

    def folder(self, folder: Path, *, companions: dict[str, bool], numbered_from_zero: bool) -> None:
        """Check one frame folder (a Semantic-NeRF sequence or a DM-NeRF scene).

        Args:
            companions: per-frame file kinds besides rgb -> required (an optional kind is checked if its folder exists).
            numbered_from_zero: frames must be numbered 0..N-1 (DM-NeRF names files from the pose index).
        """
        rgb = self.scan(folder, RGB_DIR, required=True)
        numbers = sorted(rgb) if rgb else []
        rows = self.trajectory(folder / TRAJECTORY_FILE, numbers)
        if rgb is None:
            return
        if not rgb:
            self.problem(folder / RGB_DIR, None, "rgb_<i>.png frames", "none")
            return
        if rows is not None and rows != len(rgb):
            self.problem(folder / TRAJECTORY_FILE, None, f"{len(rgb)} pose rows, one per rgb frame", f"{rows}")
        if numbered_from_zero:
            for number in sorted(set(range(len(rgb))) - set(rgb)):
                expected = f"frames numbered 0..{len(rgb) - 1}"
                self.problem(folder / RGB_DIR / f"rgb_{number}.png", number, expected, "no such file")
        others: dict[str, dict[int, Path]] = {}
        for kind, required in companions.items():
            files = self.scan(folder, kind, required)
            if files is None:
                continue
            others[kind] = files
            for number in numbers:
                if number not in files:
                    expected = f"a {kind} PNG beside rgb_{number}.png"
                    self.problem(folder / kind / f"{kind}_{number}.png", number, expected, "no such file")
            for number in sorted(set(files) - set(rgb)):
                self.problem(files[number], number, f"rgb_{number}.png for it", "no rgb frame with that number")
        size: tuple[int, int] | None = None
        instance_ids: set[int] = set()
        for number in numbers:
            image = self.image(rgb[number], number, RGB_DIR, size)
            if image is not None and size is None:
                size = image.shape[:2]
            for kind, files in others.items():
                if number not in files:
                    continue
                image = self.image(files[number], number, kind, size)
                if image is None:
                    continue
                if kind == CLASS_DIR:
                    self.labels(files[number], number, image)
                elif kind == INSTANCE_DIR:
                    instance_ids.update(np.unique(image).tolist())
        if INSTANCE_DIR in others:
            self.report.notes.append(f"{folder}: {len(instance_ids)} distinct instance ids")
        usable = rows == len(rgb) and all(pose is not None for pose in self.poses)
        if self.rays is not None and usable:
            far_away = far_away_cameras(self.poses, self.rays.far)
            for index, problem in far_away.items():
                expected = f"{problem.expected} (--far {self.rays.far:g})"
                self.problem(folder / TRAJECTORY_FILE, numbers[index], expected, problem.found)
            usable = not far_away  # pose sanity of such a scale says nothing more
        if self.rays is not None and self.hfov_deg is not None and size is not None and usable:
            intrinsics = hfov_intrinsics(size[0], size[1], self.hfov_deg)
            names = [str(number) for number in numbers]
            report_poses(self.report, folder / TRAJECTORY_FILE, self.poses, intrinsics, size, self.rays, names)

    def finish(self, found_scenes: list[str], split_files: list[str]) -> LayoutReport:
        listed = sorted({name for split in split_files for name in read_split_file(split)})
        missing = [name for name in listed if name not in found_scenes]
        extra = [name for name in found_scenes if name not in listed]
        if missing:
            self.report.notes.append(f"scenes named in the split files but absent: {', '.join(missing)}")
        if extra:
            self.report.notes.append(f"scene folders in no split file (never loaded): {', '.join(extra)}")
        self.report.present.update(self.counts)
        if self.labels_seen:
            table = raw_to_class_table()
            per_class = np.zeros(len(CLASS_NAMES) + 1, dtype=np.int64)  # last slot: ignore
            np.add.at(per_class, np.minimum(table, len(CLASS_NAMES)), self.raw_pixels)
            per_class[-1] += self.unknown_pixels
            names = (*CLASS_NAMES, "ignore")
            self.report.class_histogram = {names[i]: int(c) for i, c in enumerate(per_class.tolist()) if c}
            absent = [name for name, count in zip(CLASS_NAMES, per_class.tolist()) if not count]
            if absent:
                self.report.notes.append(f"classes without a labelled pixel ({len(absent)}): {', '.join(absent)}")
        return self.report


def _subfolders(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))


def check_replica_layout(root: Path, *, rays: RayRange | None = None, hfov_deg: float | None = None) -> LayoutReport:
    """Check ``<root>/<scene>/Sequence_<n>/{rgb,depth,semantic_class}/`` + ``traj_w_c.txt`` (Semantic-NeRF renders).

    ``class_histogram`` counts the pixels of every ``semantic_class`` frame after the 51-class mapping. With ``rays``
    and ``hfov_deg``, each sequence whose poses all parse gets pose sanity: a scale that refuses is a problem, other
    findings are notes naming the frame number.
    """
    root = Path(root)
    walk = _Walk(LayoutReport("replica", root), rays, hfov_deg)
    found = []
    for scene in _subfolders(root):
        sequences = [d for d in _subfolders(scene) if d.name.startswith("Sequence_")]
        if not sequences:
            flat = (scene / RGB_DIR).is_dir()
            hint = " (rgb/ directly inside: the DM-NeRF layout, --layout replica_instance)" if flat else ""
            walk.problem(scene, None, "Sequence_<n>/ folders", f"none{hint}")
            continue
        found.append(scene.name)
        walk.counts["scenes"] += 1
        for sequence in sequences:
            walk.counts["sequences"] += 1
            companions = {DEPTH_DIR: True, CLASS_DIR: True, INSTANCE_DIR: False}
            walk.folder(sequence, companions=companions, numbered_from_zero=False)
    if not found:
        walk.problem(root, None, "scene folders holding Sequence_<n>/ (office_0/Sequence_1/, ...)", "none")
    return walk.finish(found, [name for pair in PROTOCOL_FILES.values() for name in pair])


def check_replica_instance_layout(
    root: Path, *, rays: RayRange | None = None, hfov_deg: float | None = None
) -> LayoutReport:
    """Check ``<root>/<scene>/{rgb,depth,semantic_instance}/`` + ``traj_w_c.txt`` (DM-NeRF renders, frames 0..N-1).

    An optional ``semantic_class`` folder is checked too and fills ``class_histogram``; the notes give each scene's
    number of distinct instance ids. ``rays`` and ``hfov_deg``: pose sanity as in ``check_replica_layout``.
    """
    root = Path(root)
    walk = _Walk(LayoutReport("replica_instance", root), rays, hfov_deg)
    found = []
    for scene in _subfolders(root):
        if not (scene / RGB_DIR).is_dir() and not (scene / TRAJECTORY_FILE).is_file():
            nested = any(d.name.startswith("Sequence_") for d in _subfolders(scene))
            hint = "Sequence_<n>/ folders (the Semantic-NeRF layout, --layout replica)" if nested else "neither"
            expected = f"rgb/, depth/, semantic_instance/ and {TRAJECTORY_FILE} in the scene folder"
            walk.problem(scene, None, expected, hint)
            continue
        found.append(scene.name)
        walk.counts["scenes"] += 1
        walk.folder(scene, companions={DEPTH_DIR: True, INSTANCE_DIR: True, CLASS_DIR: False}, numbered_from_zero=True)
    if not found:
        walk.problem(root, None, "scene folders holding rgb/ and traj_w_c.txt (office_0/, ...)", "none")
    return walk.finish(found, [INSTANCE_SCENES_FILE])
