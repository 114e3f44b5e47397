"""Reading a capture's ``transforms.json`` (nerfstudio's format; Blender and instant-ngp files have the same shape).

What is read (docs/datasets/capture.md has the whole contract):

- intrinsics at the top level or per frame (a frame's own keys win): ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``,
  or Blender's ``camera_angle_x`` (``camera_angle_y``) with the size taken from the image; ``camera_model``
  ``PINHOLE`` (default), ``SIMPLE_PINHOLE`` or ``OPENCV`` with ``k1 k2 p1 p2`` (and ``k3``, 0 if absent). COLMAP and
  nerfstudio put the top-left pixel's centre at (0.5, 0.5); the framework at (0, 0), so ``cx, cy`` lose 0.5 here.
- ``frames[*].transform_matrix``: camera-to-world in the OpenGL convention (x right, y up, z backward), turned into
  the framework's OpenCV one (y and z flipped). ``applied_transform`` (a world transform ns-process-data applied to
  COLMAP's world, rigid up to a uniform scale) is undone, so the poses are in the sparse model's world.
- optional ``depth_file_path`` (16-bit PNG or ``.npy``; metres per unit from ``depth_unit_scale_factor``),
  ``mask_path`` (0 = ignore the pixel) and the extensions ``semantic_file_path`` (class-id image), ``near``, ``far``.
- nerfstudio's ``train_filenames`` / ``val_filenames`` / ``test_filenames`` where present, and ``ply_file_path`` (the
  sparse points ns-process-data exports, in the same world as the poses).

Every path stays inside the capture folder; every problem is one ``DataError`` naming the file and the key.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gpnerf_core import EXPECTED_RIGID, DataError, rigid_transform_problem
from gpnerf_plugins.datasets.common.image_io import image_size

TRANSFORMS_FILE = "transforms.json"
CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplied onto an OpenGL camera-to-world matrix: flips the camera's y and z axes (its own inverse)."""


@dataclass(frozen=True)
class CaptureCamera:
    """One frame's camera as stored, before any resize.

    Attributes:
        intrinsics: ``[3, 3]`` float64 pinhole matrix, pixel centres at integers.
        height, width: the image size the intrinsics belong to, pixels.
        distortion: OpenCV ``(k1, k2, p1, p2, k3)`` for an ``OPENCV`` camera, else None.
    """

    intrinsics: np.ndarray
    height: int
    width: int
    distortion: tuple[float, ...] | None = None


@dataclass(frozen=True)
class CaptureFrame:
    """One frame of a capture.

    Attributes:
        name: its ``file_path`` as written in the file (the frame's name in messages and split lists).
        image, depth, mask, semantic: files inside the capture folder (None where the frame has none).
        c2w: ``[4, 4]`` float64 camera-to-world, OpenCV convention, in the file's units.
        camera: intrinsics and distortion at the stored image size.
        near, far: the frame's depth bounds from the file, or None.
    """

    name: str
    image: Path
    c2w: np.ndarray
    camera: CaptureCamera
    depth: Path | None = None
    mask: Path | None = None
    semantic: Path | None = None
    near: float | None = None
    far: float | None = None


@dataclass(frozen=True)
class CaptureFile:
    """A parsed ``transforms.json``: its frames sorted by name, and what it says about splits and depth units.

    Attributes:
        held_out: names listed in ``val_filenames`` / ``test_filenames``; train: names in ``train_filenames``;
            both None when the file lists no split.
        depth_unit: metres per stored depth unit (``depth_unit_scale_factor``), or None if the file does not say.
        points: the sparse point cloud (``ply_file_path``), or None.
        world: ``[4, 4]`` the inverse of ``applied_transform`` (identity without one): maps the file's world, where
            ``points`` lie, to the poses' world.
    """

    path: Path
    frames: tuple[CaptureFrame, ...]
    train: tuple[str, ...] | None
    held_out: tuple[str, ...] | None
    depth_unit: float | None
    points: Path | None = None
    world: np.ndarray = field(default_factory=lambda: np.eye(4))


def read_transforms(path: Path) -> CaptureFile:
    """Parse and check ``path`` (a ``transforms.json``); image headers are read for sizes, pixels are not decoded."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{path}: missing; expected a capture's transforms.json (nerfstudio format)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: not readable JSON ({exc}); expected a capture's transforms.json") from None
    if not isinstance(data, dict):
        raise DataError(f"{path}: a JSON {type(data).__name__}; expected an object with 'frames'")
    frames_data = data.get("frames")
    if not isinstance(frames_data, list) or not frames_data:
        raise DataError(f"{path}: 'frames' is missing or empty; expected a list of frames with file_path and "
                        "transform_matrix")
    world = _world_undo(path, data.get("applied_transform"))
    frames = []
    for index, frame in enumerate(frames_data):
        if not isinstance(frame, dict):
            raise DataError(f"{path}: frames[{index}] is a {type(frame).__name__}; expected an object")
        frames.append(_frame(path, index, frame, data, world))
    names = [f.name for f in frames]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise DataError(f"{path}: frame file_path {repeated[0]!r} appears twice; expected each image once")
    frames.sort(key=lambda f: f.name)
    depth_unit = data.get("depth_unit_scale_factor")
    if depth_unit is not None and not _positive(depth_unit):
        raise DataError(f"{path}: depth_unit_scale_factor={depth_unit!r}; expected metres per depth unit > 0")
    points = _inside(path, str(data["ply_file_path"]), str(path), "ply_file_path") if data.get("ply_file_path") else None
    return CaptureFile(path, tuple(frames), _names(path, data, ("train_filenames",), names),
                       _names(path, data, ("val_filenames", "test_filenames"), names),
                       float(depth_unit) if depth_unit is not None else None, points, world)


def _frame(path: Path, index: int, frame: dict[str, Any], top: dict[str, Any], world: np.ndarray) -> CaptureFrame:
    where = f"{path}: frames[{index}]"
    if "file_path" not in frame:
        raise DataError(f"{where} has no 'file_path'; expected the image's path relative to {path.parent}")
    name = str(frame["file_path"])
    where = f"{path}: frame {name!r}"
    image = _inside(path, name, where, "file_path")
    if "transform_matrix" not in frame:
        raise DataError(f"{where} has no 'transform_matrix'; expected its 4x4 camera-to-world matrix")
    c2w = _matrix(frame["transform_matrix"], (4, 4), where, "transform_matrix")
    problem = rigid_transform_problem(c2w)
    if problem is not None:
        raise DataError(f"{where}: transform_matrix has {problem}; expected {EXPECTED_RIGID}")
    c2w = _in_world(world, c2w) @ OPENGL_TO_OPENCV
    optional = {}
    for key, attribute in (("depth_file_path", "depth"), ("mask_path", "mask"), ("semantic_file_path", "semantic")):
        if frame.get(key):
            optional[attribute] = _inside(path, str(frame[key]), where, key)
    for key in ("near", "far"):
        if key in frame:
            if not _positive(frame[key]):
                raise DataError(f"{where}: {key}={frame[key]!r}; expected a depth bound in the capture's units > 0")
            optional[key] = float(frame[key])
    if "near" in optional and "far" in optional and optional["near"] >= optional["far"]:
        raise DataError(f"{where}: near={optional['near']} >= far={optional['far']}; expected near < far")
    return CaptureFrame(name, image, c2w, _camera(frame, top, image, where), **optional)


def _camera(frame: dict[str, Any], top: dict[str, Any], image: Path, where: str) -> CaptureCamera:
    """Intrinsics of one frame (its own keys first, then the file's), checked against the image's header."""

    def value(key: str) -> Any:
        return frame[key] if key in frame else top.get(key)

    model = str(value("camera_model") or "PINHOLE").upper()
    if model not in CAMERA_MODELS:
        raise DataError(f"{where}: camera_model={model!r}; expected one of {', '.join(CAMERA_MODELS)} (undistort "
                        "other models first, e.g. with `data import-colmap`)")
    height, width = image_size(image, "an image (PNG or JPEG)")
    for key, actual in (("w", width), ("h", height)):
        stated = value(key)
        if stated is not None and (not _positive(stated) or int(stated) != actual):
            raise DataError(f"{image}: image is {width}x{height} but {key}={stated!r}; expected the image's own size "
                            "(intrinsics belong to the stored image)")
    if value("fl_x") is not None:
        fx = value("fl_x")
        fy = value("fl_y") if value("fl_y") is not None else fx
        cx = value("cx") if value("cx") is not None else width / 2
        cy = value("cy") if value("cy") is not None else height / 2
    elif value("camera_angle_x") is not None:
        angle_x = value("camera_angle_x")
        if not _positive(angle_x) or angle_x >= math.pi:
            raise DataError(f"{where}: camera_angle_x={angle_x!r}; expected a field of view in radians in (0, pi)")
        fx = 0.5 * width / math.tan(0.5 * float(angle_x))
        angle_y = value("camera_angle_y")
        fy = 0.5 * height / math.tan(0.5 * float(angle_y)) if _positive(angle_y) else fx
        cx, cy = width / 2, height / 2
    else:
        raise DataError(f"{where}: no intrinsics; expected fl_x (fl_y, cx, cy) or camera_angle_x, per frame or at "
                        "the top of the file")
    for key, number in (("fl_x", fx), ("fl_y", fy)):
        if not _positive(number):
            raise DataError(f"{where}: {key}={number!r}; expected a focal length in pixels > 0")
    for key, number in (("cx", cx), ("cy", cy)):
        if not _finite(number):
            raise DataError(f"{where}: {key}={number!r}; expected a principal point in pixels")
    k = np.array([[float(fx), 0.0, float(cx) - 0.5], [0.0, float(fy), float(cy) - 0.5], [0.0, 0.0, 1.0]])
    distortion = None
    if model == "OPENCV":
        coefficients = []
        for key in ("k1", "k2", "p1", "p2", "k3"):
            number = value(key) if value(key) is not None else 0.0
            if not _finite(number):
                raise DataError(f"{where}: {key}={number!r}; expected a finite OPENCV distortion coefficient")
            coefficients.append(float(number))
        distortion = tuple(coefficients) if any(coefficients) else None
    return CaptureCamera(k, height, width, distortion)


def _world_undo(path: Path, applied: Any) -> np.ndarray:
    """The 4x4 inverse of ``applied_transform`` (identity without one)."""
    if applied is None:
        return np.eye(4)
    rows = np.asarray(applied, dtype=object)
    shape = (4, 4) if rows.shape == (4, 4) else (3, 4)
    matrix = np.eye(4)
    matrix[:3] = _matrix(applied, shape, str(path), "applied_transform")[:3]
    scale = float(np.cbrt(np.linalg.det(matrix[:3, :3])))
    if not scale > 0 or rigid_transform_problem(_rigid_part(matrix, scale)) is not None:
        raise DataError(f"{path}: applied_transform is not a rotation and translation with one uniform scale; "
                        "expected the 3x4 world transform nerfstudio records")
    return np.linalg.inv(matrix)


def _rigid_part(matrix: np.ndarray, scale: float) -> np.ndarray:
    """``matrix`` with its rotation block divided by ``scale``."""
    rigid = np.eye(4)
    rigid[:3, :3] = matrix[:3, :3] / scale
    rigid[:3, 3] = matrix[:3, 3]
    return rigid


def _in_world(undo: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """``undo @ c2w`` with the uniform scale of ``undo`` moved out of the rotation (the camera stays rigid)."""
    moved = undo @ c2w
    scale = float(np.cbrt(np.linalg.det(undo[:3, :3])))
    moved[:3, :3] /= scale
    return moved


def _matrix(values: Any, shape: tuple[int, int], where: str, key: str) -> np.ndarray:
    try:
        matrix = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}: {key} is not a matrix of numbers; expected {shape[0]}x{shape[1]} numbers") from None
    if matrix.shape != shape:
        raise DataError(f"{where}: {key} has shape {list(matrix.shape)}; expected {shape[0]}x{shape[1]}")
    if not np.isfinite(matrix).all():
        raise DataError(f"{where}: {key} holds NaN or Inf; expected finite numbers")
    return matrix


def _inside(path: Path, relative: str, where: str, key: str) -> Path:
    """``relative`` resolved against the capture folder; refused if it leaves it (``../``, an absolute path)."""
    folder = path.parent.resolve()
    target = (folder / relative).resolve()
    if not target.is_relative_to(folder):
        raise DataError(f"{where}: {key}={relative!r} leaves the capture folder {folder}; expected a path inside it")
    return target


def _names(path: Path, data: dict[str, Any], keys: tuple[str, ...], known: list[str]) -> tuple[str, ...] | None:
    listed: list[str] = []
    present = False
    for key in keys:
        if key in data:
            present = True
            if not isinstance(data[key], list):
                raise DataError(f"{path}: {key} is a {type(data[key]).__name__}; expected a list of file paths")
            listed += [str(n) for n in data[key]]
    if not present:
        return None
    unknown = [n for n in listed if n not in known]
    if unknown:
        raise DataError(f"{path}: {keys[0]} names {unknown[0]!r}, which no frame has; expected frames' file_path")
    return tuple(listed)


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _positive(value: Any) -> bool:
    return _finite(value) and value > 0
