"""``check_scannet_layout``: walk a ScanNet (Semantic-Ray export) folder and report everything missing or malformed."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
from PIL import Image

from gpnerf_core import DataError, depth_problem, far_away_cameras
from gpnerf_plugins.datasets.common.image_io import one_line_error
from gpnerf_plugins.datasets.common.layout_check import LayoutReport
from gpnerf_plugins.datasets.common.pose_report import RayRange, report_poses
from gpnerf_plugins.datasets.scannet.files import (
    COLOR_DIR,
    DEPTH_DIR,
    DEPTH_SCALE,
    INSTANCE_DIR,
    INTEGER_MODES,
    INTRINSIC_COLOR,
    LABEL_DIR,
    POSE_DIR,
    SCENE_NAME,
    FrameFiles,
    LayoutError,
    aspect_mismatch,
    decode_image,
    image_size,
    pose_is_valid,
    read_integer_image,
    read_intrinsic,
    read_pose,
    scan_frames,
)
from gpnerf_plugins.datasets.scannet.labels import (
    IGNORE_INDEX,
    LABEL_MAP_NAME,
    SCANNET20_CLASS_NAMES,
    LabelMap,
    read_label_map,
)
from gpnerf_plugins.datasets.scannet.splits import read_split

IGNORE_NAME = "ignore"


def _jpeg_complete(path: Path, frame: str) -> None:
    """Raise ``LayoutError`` for a JPEG that is truncated: no end-of-image marker AND a failing full decode."""
    with path.open("rb") as handle:
        head = handle.read(2)
        handle.seek(max(0, path.stat().st_size - 2))
        tail = handle.read(2)
    if head != b"\xff\xd8":
        raise LayoutError(path, "a JPEG (starting with the marker FFD8)", f"first bytes {head.hex() or 'none'}", frame)
    if tail != b"\xff\xd9":
        decode_image(path, frame, "JPEG colour image")  # trailing bytes after the marker are legal: decode decides


def _png_complete(path: Path, frame: str, kind: str) -> tuple[int, int]:
    """Header and CRC check of a single-channel integer PNG (no pixel decoding); returns ``(H, W)``."""
    try:
        with Image.open(path) as image:
            fmt, mode, (width, height) = image.format, image.mode, image.size
            image.verify()
    except Exception as exc:
        raise LayoutError(path, f"a complete {kind} PNG", one_line_error(exc), frame) from None
    if fmt != "PNG":
        raise LayoutError(path, f"a {kind} PNG", f"a {fmt} file", frame)
    if mode not in INTEGER_MODES:
        raise LayoutError(path, f"a single-channel integer {kind} PNG", f"mode {mode}", frame)
    if kind == "depth" and mode == "L":
        raise LayoutError(path, "a 16-bit depth PNG (millimetres)", "an 8-bit PNG (at most 0.255 m)", frame)
    return height, width


class _SceneCheck:
    """Checks of one scene folder, appending to a shared report."""

    def __init__(self, report: LayoutReport, path: Path, label_map: LabelMap | None, histogram_every: int,
                 rays: RayRange | None = None) -> None:
        self.report, self.path, self.label_map, self.every = report, path, label_map, histogram_every
        self.rays = rays
        self.invalid_poses = 0
        self.poses: dict[str, np.ndarray] = {}  # finite rigid poses by frame token (the frames the loader keeps)
        self.unknown_ids: Counter[int] = Counter()

    def problem(self, error: LayoutError) -> None:
        self.report.problems.append(error.problem)

    def count(self, kind: str, n: int) -> None:
        self.report.present[kind] = self.report.present.get(kind, 0) + n

    def run(self) -> None:
        frames, problems = scan_frames(self.path)
        for error in problems:
            self.problem(error)
        kinds = [
            ("color", COLOR_DIR, ".jpg"),
            ("depth", DEPTH_DIR, ".png"),
            ("label-filt", LABEL_DIR, ".png"),
            ("pose", POSE_DIR, ".txt"),
        ]
        if (self.path / INSTANCE_DIR).is_dir():  # optional: counted only where a scene has it
            kinds.append(("instance-filt", INSTANCE_DIR, ".png"))
        for kind, folder, suffix in kinds:
            names = {p.stem for p in (self.path / folder).glob(f"*{suffix}")}
            self.count(kind, len(names))
            if kind != "color":
                orphans = names - {p.stem for p in (self.path / COLOR_DIR).glob("*.jpg")}
                if orphans:
                    self.report.notes.append(
                        f"{self.path.name}: {len(orphans)} {folder}/ files without a colour image "
                        "(ignored by the loader)"
                    )
        intrinsic = None
        try:
            intrinsic = read_intrinsic(self.path / INTRINSIC_COLOR)
        except LayoutError as error:
            self.problem(error)
        reference = None
        for position, files in enumerate(frames):
            reference = self.frame(files, position, reference)
        if self.rays is not None and self.poses and not self.far_away_cameras() and intrinsic is not None \
                and reference is not None:
            tokens = list(self.poses)
            poses = [self.poses[token] for token in tokens]
            report_poses(self.report, self.path / POSE_DIR, poses, intrinsic, reference, self.rays, tokens)
        self.count("frames", len(frames))
        self.count("invalid poses", self.invalid_poses)
        if self.invalid_poses:
            self.report.notes.append(
                f"{self.path.name}: {self.invalid_poses} of {len(frames)} frames have an invalid (non-finite) pose; "
                "the loader drops them with their images"
            )
        if self.unknown_ids:
            ids = sorted(self.unknown_ids)
            shown = ", ".join(map(str, ids[:8])) + (", ..." if len(ids) > 8 else "")
            self.report.notes.append(
                f"{self.path.name}: {sum(self.unknown_ids.values())} label pixels have ids absent from the label map "
                f"({shown}); they count as {IGNORE_NAME}"
            )

    def frame(self, files: FrameFiles, position: int, reference: tuple[int, int] | None) -> tuple[int, int] | None:
        """Check one frame's files (and its instance PNG, if any); returns the colour size the scene's frames share."""
        try:
            pose = read_pose(files.pose, files.token)
            if not pose_is_valid(pose):
                self.invalid_poses += 1
            else:
                self.poses[files.token] = pose
        except LayoutError as error:
            self.problem(error)
        try:
            size = image_size(files.color, files.token)
            _jpeg_complete(files.color, files.token)
            if reference is None:
                reference = size
            elif size != reference:
                self.problem(
                    LayoutError(
                        files.color,
                        f"{reference[1]}x{reference[0]} (WxH) like the scene's first frame",
                        f"{size[1]}x{size[0]}",
                        files.token,
                    )
                )
        except LayoutError as error:
            self.problem(error)
        label_ok = depth_ok = False
        images = [(files.depth, "depth"), (files.label, "label")]
        if files.instance is not None:
            images.append((files.instance, "instance"))
        for path, kind in images:
            try:
                size = _png_complete(path, files.token, kind)
                if reference is not None and aspect_mismatch(size, reference):
                    raise LayoutError(
                        path,
                        f"the colour aspect ratio ({reference[1]}x{reference[0]})",
                        f"{size[1]}x{size[0]}",
                        files.token,
                    )
                label_ok = label_ok or kind == "label"
                depth_ok = depth_ok or kind == "depth"
            except LayoutError as error:
                self.problem(error)
        if label_ok and self.label_map is not None and position % self.every == 0:
            self.histogram(files)
        if depth_ok and self.rays is not None and position % self.every == 0:
            self.depth_values(files)
        return reference

    def far_away_cameras(self) -> bool:
        """Report the cameras absurdly far from the others (``gpnerf_core.data.checks``); True if there are any."""
        assert self.rays is not None
        tokens = list(self.poses)
        found = far_away_cameras([self.poses[token] for token in tokens], self.rays.far)
        for index, problem in found.items():
            expected = f"{problem.expected} (--far {self.rays.far:g})"
            path = self.path / POSE_DIR / f"{tokens[index]}.txt"
            self.problem(LayoutError(path, expected, problem.found, tokens[index]))
        return bool(found)

    def depth_values(self, files: FrameFiles) -> None:
        """The depth map's values as ``dataset.validate`` checks them (``gpnerf_core.data.checks.depth_problem``)."""
        assert self.rays is not None
        try:
            stored = read_integer_image(files.depth, files.token, "depth")
        except LayoutError as error:
            self.problem(error)
            return
        problem = depth_problem(stored.astype(np.float64) / DEPTH_SCALE, self.rays.far)
        if problem is not None:
            expected = f"{problem.expected} (--far {self.rays.far:g})"
            self.problem(LayoutError(files.depth, expected, problem.found, files.token))

    def histogram(self, files: FrameFiles) -> None:
        try:
            raw = read_integer_image(files.label, files.token, "label")
        except LayoutError as error:
            self.problem(error)
            return
        assert self.label_map is not None
        labels, unknown, _ = self.label_map.apply(raw)
        for value in unknown:
            self.unknown_ids[int(value)] += int((raw == value).sum())
        counts = np.bincount(labels.ravel(), minlength=IGNORE_INDEX + 1)
        histogram = self.report.class_histogram
        for class_id, name in enumerate(SCANNET20_CLASS_NAMES):
            histogram[name] += int(counts[class_id])
        histogram[IGNORE_NAME] += int(counts[IGNORE_INDEX])


def check_scannet_layout(
    root: str | Path,
    *,
    label_map_file: str | Path | None = None,
    histogram_every: int = 10,
    rays: RayRange | None = None,
) -> LayoutReport:
    """Walk ``root`` (the folder of ``sceneXXXX_YY`` folders) against the ScanNet layout.

    Every frame's four files (and its ``instance-filt`` PNG where the scene has that folder) are checked without
    decoding pixels (headers, PNG CRCs, the JPEG end marker, pose and intrinsic numbers); labels of every
    ``histogram_every``-th frame of each scene are decoded for the class histogram (20 classes + ignore), and with
    ``rays`` their depth maps too (refused when every known depth is beyond ``far``; an 8-bit depth PNG is refused from
    its header). A scene
    whose ``instance-filt/`` lacks a frame's PNG is a problem; a scene without the folder is fine. Invalid poses
    and label ids the tsv lacks are notes, not problems: the loader handles them. With ``rays``, the frames with a
    valid pose get pose sanity (``gpnerf_core.geometry.pose_sanity``, colour intrinsics at the colour size): a scale that
    refuses is a problem, other findings are notes naming the frame; a camera absurdly far from the others
    (``gpnerf_core.data.checks.far_away_cameras``) is a problem, as ``dataset.validate`` has it.

    Args:
        root: the dataset folder.
        label_map_file: the tsv; default ``<root>/scannetv2-labels.combined.tsv``.
        histogram_every: decode the labels of one frame in this many (1 = all; decoding dominates the run time).
        rays: the ray range pose sanity measures the cameras' scale against; None = no pose sanity.
    """
    root = Path(root)
    if histogram_every < 1:
        raise DataError(f"histogram_every={histogram_every}; expected 1 or more")
    report = LayoutReport(layout="scannet", root=root)
    tsv = Path(label_map_file) if label_map_file is not None else root / LABEL_MAP_NAME
    label_map = None
    try:
        label_map = read_label_map(tsv)
        report.class_histogram = {name: 0 for name in (*SCANNET20_CLASS_NAMES, IGNORE_NAME)}
    except LayoutError as error:
        report.problems.append(error.problem)
        report.notes.append("no class histogram: the label map could not be read")
    folders = sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
    scenes = [p for p in folders if SCENE_NAME.match(p.name)]
    others = [p.name for p in folders if not SCENE_NAME.match(p.name)]
    if others:
        report.notes.append(f"ignored {len(others)} folders not named sceneXXXX_YY: {', '.join(others[:5])}")
    report.present["scenes"] = len(scenes)
    if not scenes:
        report.problems.append(LayoutError(root, "sceneXXXX_YY scene folders", "none").problem)
    for scene in scenes:
        _SceneCheck(report, scene, label_map, histogram_every, rays).run()
    names = {p.name for p in scenes}
    for split, listed in (("train", read_split("train")), ("unseen (test)", read_split("test"))):
        report.notes.append(f"{split} split: {len(names & set(listed))} of its {len(listed)} scenes present")
    if scenes:
        with_instances = sum((scene / INSTANCE_DIR).is_dir() for scene in scenes)
        report.notes.append(f"instance maps ({INSTANCE_DIR}/, optional): {with_instances} of {len(scenes)} scenes")
    if label_map is not None:
        report.notes.append(f"class histogram from the labels of one frame in {histogram_every} of each scene")
    return report
