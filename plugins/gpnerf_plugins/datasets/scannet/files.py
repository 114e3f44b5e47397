"""Files of one scene in the ScanNet (Semantic-Ray export) layout: listing, pose and intrinsics parsing, image I/O.

A scene folder ``<root>/sceneXXXX_YY/`` holds, for every frame ``<f>`` (an integer, the frame's index in the
``.sens`` stream)::

    color/<f>.jpg                    colour image (1296 x 968 in ScanNet)
    depth/<f>.png                    uint16 depth in millimetres, 0 = unknown (640 x 480 in ScanNet)
    label-filt/<f>.png               raw ScanNet category ids (16-bit, colour resolution)
    instance-filt/<f>.png            OPTIONAL: object instance ids of the scan (8-bit, colour resolution,
                                     0 = not annotated); when the folder exists every frame needs one
    pose/<f>.txt                     4 rows of 4 numbers: camera-to-world, OpenCV camera, metres;
                                     all -inf (or any NaN/Inf) marks a frame the tracker lost
    intrinsic/intrinsic_color.txt    4 x 4 pinhole matrix of the colour image (top-left 3 x 3 used)

Loader and checker share these parsers; every problem is a ``LayoutError`` carrying path, frame, expected, found.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from gpnerf_core import EXPECTED_RIGID, DataError, rigid_transform_problem
from gpnerf_plugins.datasets.common import image_io
from gpnerf_plugins.datasets.common.image_io import ImageError
from gpnerf_plugins.datasets.common.layout_check import Problem

COLOR_DIR, DEPTH_DIR, LABEL_DIR, POSE_DIR = "color", "depth", "label-filt", "pose"
INSTANCE_DIR = "instance-filt"
"""Optional: ScanNet's 2D instance maps (``<scan>_2d-instance-filt.zip``); present for all frames of a scene or none."""
INTRINSIC_COLOR = Path("intrinsic") / "intrinsic_color.txt"
INTRINSIC_DEPTH = Path("intrinsic") / "intrinsic_depth.txt"
DEPTH_SCALE = 1000.0  # depth PNG units per metre
SCENE_NAME = re.compile(r"^scene\d{4}_\d{2}$")
INTEGER_MODES = ("L", "I", "I;16", "I;16B", "I;16L")
"""PIL modes of a single-channel integer (8/16/32-bit) PNG."""


class LayoutError(DataError):
    """A missing or malformed file of the layout; the message is one line, like ``Problem.__str__``."""

    def __init__(self, path: Path | str, expected: str, found: str, frame: str | None = None) -> None:
        self.problem = Problem(str(path), frame, expected, found)
        super().__init__(str(self.problem))


@dataclass(frozen=True)
class FrameFiles:
    """The files of frame ``token`` (the file stem, e.g. ``"10"``; ``number`` is its integer value).

    ``instance`` is ``instance-filt/<token>.png`` when that file exists, else None (the scene has no instance maps,
    or this frame's is missing, which ``scan_frames`` reports).
    """

    token: str
    number: int
    color: Path
    depth: Path
    label: Path
    pose: Path
    instance: Path | None = None


def scan_frames(scene_dir: Path) -> tuple[list[FrameFiles], list[LayoutError]]:
    """List the frames of a scene in NUMERIC order and every problem of the listing.

    A frame is a ``color/<f>.jpg``; it needs ``depth/<f>.png``, ``label-filt/<f>.png`` and ``pose/<f>.txt``.
    Frames missing a companion are left out of the list and reported, as are ``.jpg`` names that are not
    integers and two names for one number (``7.jpg``, ``07.jpg``). Other files in ``color/`` are ignored.
    When ``instance-filt/`` exists, a frame without ``instance-filt/<f>.png`` is reported too but kept (its
    ``instance`` is None). Problems come in numeric frame order, so the first one names the lowest frame.
    """
    color_dir = scene_dir / COLOR_DIR
    if not color_dir.is_dir():
        return [], [LayoutError(color_dir, "a folder of <frame>.jpg colour images", "nothing")]
    has_instances = (scene_dir / INSTANCE_DIR).is_dir()
    frames: list[FrameFiles] = []
    problems: list[LayoutError] = []
    for path in sorted(color_dir.iterdir(), key=_frame_order):
        if path.suffix != ".jpg" or not path.is_file():
            continue  # not a colour frame (e.g. a stray thumbnail); frames are the .jpg files
        token = path.stem
        if not token.isdigit():
            problems.append(LayoutError(path, "a numeric frame name <integer>.jpg", f"{path.name!r}", token))
            continue
        instance = scene_dir / INSTANCE_DIR / f"{token}.png"
        files = FrameFiles(
            token,
            int(token),
            path,
            scene_dir / DEPTH_DIR / f"{token}.png",
            scene_dir / LABEL_DIR / f"{token}.png",
            scene_dir / POSE_DIR / f"{token}.txt",
            instance if instance.is_file() else None,
        )
        missing = [p for p in (files.depth, files.label, files.pose) if not p.is_file()]
        for companion in missing:
            problems.append(LayoutError(companion, f"a file beside {COLOR_DIR}/{path.name}", "nothing", token))
        if has_instances and files.instance is None:
            expected = f"a file beside {COLOR_DIR}/{path.name} ({INSTANCE_DIR}/ exists, so every frame needs one)"
            problems.append(LayoutError(instance, expected, "nothing", token))
        if not missing:
            frames.append(files)
    frames.sort(key=lambda f: f.number)
    for a, b in zip(frames, frames[1:]):
        if a.number == b.number:
            problems.append(
                LayoutError(b.color, f"one file per frame number (also named {a.color.name})", b.color.name, b.token)
            )
    return frames, problems


def _frame_order(path: Path) -> tuple[int, int, str]:
    """Sort key of ``color/`` entries: numeric names by value first, then anything else by name."""
    return (0, int(path.stem), path.name) if path.stem.isdigit() else (1, 0, path.name)


def _read_matrix(path: Path, what: str, frame: str | None) -> np.ndarray:
    """A text file of 4 rows of 4 numbers -> ``[4, 4]`` float64 (NaN/Inf allowed here)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise LayoutError(path, f"a {what} (4 rows of 4 numbers)", "nothing", frame) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LayoutError(path, f"a {what} (4 rows of 4 numbers)", f"an unreadable file ({exc})", frame) from None
    rows = [line.split() for line in text.splitlines() if line.strip()]
    shape = f"{len(rows)} rows of {sorted({len(r) for r in rows}) or [0]} numbers"
    if len(rows) != 4 or any(len(r) != 4 for r in rows):
        raise LayoutError(path, f"a {what} (4 rows of 4 numbers)", shape, frame)
    try:
        return np.array([[float(v) for v in r] for r in rows], dtype=np.float64)
    except ValueError:
        bad = next(v for r in rows for v in r if not _is_float(v))
        raise LayoutError(path, f"a {what} (4 rows of 4 numbers)", f"the non-number {bad!r}", frame) from None


def _is_float(value: str) -> bool:
    try:
        float(value)
    except ValueError:
        return False
    return True


def read_pose(path: Path, frame: str | None = None) -> np.ndarray:
    """``pose/<f>.txt`` -> ``[4, 4]`` float64 camera-to-world; non-finite entries mean an invalid pose (returned as is).

    Raises:
        LayoutError: not 4 x 4 numbers, or a finite pose that is not a rigid transform.
    """
    pose = _read_matrix(path, "camera-to-world pose", frame)
    problem = rigid_transform_problem(pose) if np.isfinite(pose).all() else None
    if problem is not None:
        raise LayoutError(path, EXPECTED_RIGID, problem, frame)
    return pose


def pose_is_valid(pose: np.ndarray) -> bool:
    """False for the poses ScanNet marks invalid (-inf), or any NaN/Inf."""
    return bool(np.isfinite(pose).all())


def read_intrinsic(path: Path) -> np.ndarray:
    """``intrinsic/intrinsic_color.txt`` -> ``[3, 3]`` float64 pinhole matrix (top-left block of the 4 x 4).

    Raises:
        LayoutError: missing, not 4 x 4 numbers, non-finite, non-positive focal lengths or a last row not ``0 0 1``.
    """
    matrix = _read_matrix(path, "4 x 4 intrinsic matrix", None)
    k = matrix[:3, :3]
    if not np.isfinite(k).all():
        raise LayoutError(path, "finite intrinsics", "NaN or Inf")
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise LayoutError(path, "positive focal lengths fx, fy", f"fx={k[0, 0]}, fy={k[1, 1]}")
    if np.abs(k[2] - (0.0, 0.0, 1.0)).max() > 1e-6:
        raise LayoutError(path, "third row 0 0 1 (a pinhole matrix)", f"{k[2].tolist()}")
    return k


def _layout_error(error: ImageError, missing: str, unreadable: str, frame: str | None) -> LayoutError:
    """``error`` as a layout problem: expected ``missing``, found nothing; or expected ``unreadable``, found why."""
    if error.missing:
        return LayoutError(error.path, missing, "nothing", frame)
    return LayoutError(error.path, unreadable, error.reason, frame)


def image_size(path: Path, frame: str | None = None) -> tuple[int, int]:
    """``(H, W)`` from the image header, without decoding."""
    try:
        return image_io.image_size(path)
    except ImageError as error:
        raise _layout_error(error, "an image", "a readable image", frame) from None


def decode_image(path: Path, frame: str | None, kind: str) -> Image.Image:
    """Fully decode an image (a truncated or corrupt file raises ``LayoutError``, never a PIL traceback)."""
    try:
        return image_io.decode_image(path)
    except ImageError as error:
        raise _layout_error(error, kind, f"a complete {kind}", frame) from None


def read_integer_image(path: Path, frame: str | None, kind: str) -> np.ndarray:
    """A single-channel integer ``kind`` PNG (depth, label, instance) as ``[H, W]`` int64."""
    image = decode_image(path, frame, f"{kind} PNG")
    if image.mode not in INTEGER_MODES:
        raise LayoutError(path, f"a single-channel integer {kind} PNG", f"mode {image.mode}", frame)
    array = np.asarray(image)
    if kind == "depth" and array.dtype == np.uint8:
        raise LayoutError(path, "a 16-bit depth PNG (millimetres)", "an 8-bit PNG (at most 0.255 m)", frame)
    return array.astype(np.int64)


def aspect_mismatch(size: tuple[int, int], reference: tuple[int, int], tolerance: float = 0.02) -> bool:
    """True when ``(H, W)`` has an aspect ratio more than ``tolerance`` (relative) away from ``reference``'s.

    ScanNet depth (640 x 480, 4:3) and colour (1296 x 968) differ by 0.4%, which passes.
    """
    ratio = (size[1] / size[0]) / (reference[1] / reference[0])
    return abs(ratio - 1.0) > tolerance
