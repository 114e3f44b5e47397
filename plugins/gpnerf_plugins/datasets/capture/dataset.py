"""The ``capture`` dataset: a user's own captures in nerfstudio's ``transforms.json`` format (docs/datasets/capture.md).

``dataset.root`` holds one capture (``transforms.json`` in it) or one folder per capture. Frames are undistorted
(``OPENCV`` cameras), resized to the dataset's size with their intrinsics scaled, and their poses (and depths and
depth bounds) multiplied by ``dataset.scale``. A capture without semantic labels is a scene with ``labelled=False``:
its frames' labels are all the ignore index, and label metrics are not computed on it.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from gpnerf_core import (
    MAX_FAR,
    ConfigError,
    DataError,
    DatasetBase,
    DatasetConfig,
    Frame,
    Scene,
    ScenePoints,
    check_image_size,
    from_launch_dir,
)
from gpnerf_plugins.datasets.capture.points import check_finite_points, read_point_cloud
from gpnerf_plugins.datasets.capture.transforms import TRANSFORMS_FILE, CaptureFile, CaptureFrame, read_transforms
from gpnerf_plugins.datasets.capture.undistort import Undistorter
from gpnerf_plugins.datasets.common.cameras import scale_intrinsics
from gpnerf_plugins.datasets.common.decoding import FrameDecoder, FrameFiles
from gpnerf_plugins.datasets.common.image_io import decode_image, resize_nearest, resize_rgb
from gpnerf_plugins.datasets.common.scene_lists import chosen_scenes, chosen_unseen, missing_scene

CLASSES_FILE = "classes.json"
DEFAULT_DEPTH_UNIT = 1e-3
"""Metres per stored depth unit when neither the file nor ``dataset.depth_unit`` says (nerfstudio's default: mm)."""
SIZE_MULTIPLE = 16
"""Automatic sizes are multiples of this (the feature extractors' coarsest stride)."""
DEPTH_PERCENTILES = (1.0, 99.0)
DEPTH_MARGIN = 0.1
"""Bounds from depth maps: the 1st and 99th percentiles of the valid depths, widened by 10% on each side."""
DEPTH_FRAMES = 8
"""Frames (spread over the capture) whose depth maps give the bounds when the file has none."""


@dataclass
class CaptureScenesConfig(DatasetConfig):
    """Options of the captures under ``root``.

    ``root`` holds ``transforms.json`` (one capture, named after the folder) or folders that each hold one. A size of 0
    is automatic: the first frame's aspect, the long side ``long_side``, both multiples of 16. ``near``/``far`` of 0
    are taken from the capture: the frames' ``near``/``far`` (``data import-colmap`` writes them), else its depth maps.
    """

    name: str = "capture"
    """Registry name of this dataset."""
    height: int = 0
    """Image height frames are loaded at, pixels (0 = automatic, see long_side)."""
    width: int = 0
    """Image width frames are loaded at, pixels (0 = automatic, see long_side)."""
    long_side: int = 160
    """Automatic size: the long side in pixels (the short one follows the capture's aspect)."""
    near: float = 0.0
    """Ray-sampling near bound, metres after ``scale`` (0 = from the capture)."""
    far: float = 0.0
    """Ray-sampling far bound, metres after ``scale`` (0 = from the capture)."""
    eval_every: int = 8
    """Without split lists in the file, every eval_every-th frame (from frame eval_every // 2) is held out; 0 = none."""
    scale: float = 1.0
    """Multiplies camera positions, depths and depth bounds: brings a capture in arbitrary units (COLMAP's) to metres."""
    depth_unit: float = 0.0
    """Metres per stored depth unit (0 = the file's depth_unit_scale_factor, else 0.001)."""
    classes_file: str = ""
    """A classes.json ({"classes": [...], "ignore_index": 255}) for every capture; "" = each capture's own or root's."""
    labels_from: str = ""
    """A folder ``python -m gpnerf_core label`` wrote for one capture (its labels.json and labels/): that capture's
    frames take the model's predicted labels, at the dataset's size, and its classes (the label-free path)."""
    scenes: list[str] = field(default_factory=list)
    """Captures trained on (folder names under root); empty = every capture not in unseen_scenes."""
    unseen_scenes: Optional[list[str]] = None
    """Captures never trained on, evaluated for generalization; null or [] = none."""


@dataclass(frozen=True)
class ClassList:
    names: tuple[str, ...]
    ignore_index: int
    path: Path


class CaptureScenes(DatasetBase):
    """Captures in nerfstudio's format under ``root`` (construction touches no file)."""

    def __init__(
        self,
        root: str = CaptureScenesConfig.root,
        height: int = CaptureScenesConfig.height,
        width: int = CaptureScenesConfig.width,
        long_side: int = CaptureScenesConfig.long_side,
        near: float = CaptureScenesConfig.near,
        far: float = CaptureScenesConfig.far,
        eval_every: int = CaptureScenesConfig.eval_every,
        scale: float = CaptureScenesConfig.scale,
        depth_unit: float = CaptureScenesConfig.depth_unit,
        classes_file: str = CaptureScenesConfig.classes_file,
        labels_from: str = CaptureScenesConfig.labels_from,
        validate: str = CaptureScenesConfig.validate,
        scenes: Sequence[str] = (),
        unseen_scenes: Sequence[str] | None = None,
    ) -> None:
        holds = f"a capture ({TRANSFORMS_FILE} in it) or folders of captures"
        if not root:  # refused before any file is read (the base resolves the root on first use)
            raise ConfigError(f"dataset.root is empty; expected the folder holding {holds}")
        super().__init__(root=root, validate=validate, near=near, far=far, root_holds=holds, automatic_bounds=True)
        size = check_image_size(height, width, zero="automatic", multiple=SIZE_MULTIPLE)
        if long_side < SIZE_MULTIPLE:
            raise ConfigError(f"dataset.long_side={long_side}: expected at least {SIZE_MULTIPLE} pixels")
        if not scale > 0 or scale == float("inf"):
            raise ConfigError(f"dataset.scale={scale}: expected a finite factor > 0")
        if eval_every < 0:
            raise ConfigError(f"dataset.eval_every={eval_every}: expected an integer >= 0 (0 = no held-out frames)")
        if depth_unit < 0:
            raise ConfigError(f"dataset.depth_unit={depth_unit}: expected metres per depth unit > 0 (0 = the file's)")
        self.size = size or (0, 0)
        self.long_side = int(long_side)
        self.bounds = (self.near, self.far)
        self.eval_every = int(eval_every)
        self.scale = float(scale)
        self.depth_unit = float(depth_unit)
        self.classes_path = from_launch_dir(classes_file) if classes_file else None
        self.labels_from = from_launch_dir(labels_from) if labels_from else None
        self._predicted: PredictedLabels | None = None
        self._given = {"train": chosen_scenes("scenes", scenes, ()),
                       "unseen": chosen_scenes("unseen_scenes", unseen_scenes, ())}
        self._files: dict[str, CaptureFile] = {}
        self._classes: ClassList | None = None
        self._classes_read = False

    # -- scenes and splits -----------------------------------------------------------------------------------------

    def _found(self) -> dict[str, Path]:
        """Capture name -> folder: ``root`` itself when it holds transforms.json, else its subfolders that do."""
        if (self.root / TRANSFORMS_FILE).is_file():
            return {self.root.name: self.root}
        found = {p.name: p for p in sorted(self.root.iterdir()) if (p / TRANSFORMS_FILE).is_file()}
        if not found:
            raise DataError(f"{self.root}: no {TRANSFORMS_FILE} in it or in its folders; expected a capture (make one "
                            "with `data prepare-capture` or `data import-colmap`)")
        return found

    def list_scenes(self, split: str) -> tuple[str, ...]:
        found = self._found()
        self._check_predicted_scene(found)
        for key, names in (("scenes", self._given["train"]), ("unseen_scenes", self._given["unseen"])):
            for name in names:
                if name not in found:
                    raise missing_scene(self.root, name, f"a capture folder with {TRANSFORMS_FILE} (dataset.{key})")
        unseen = chosen_unseen(self._given["unseen"], (), train=self._given["train"],
                               train_given=bool(self._given["train"]))
        if split == "unseen":
            return unseen
        return self._given["train"] or tuple(name for name in found if name not in unseen)

    def capture(self, name: str) -> CaptureFile:
        """The parsed transforms.json of capture ``name``."""
        if name not in self._files:
            found = self._found()
            if name not in found:
                raise missing_scene(self.root, name, f"a capture folder with {TRANSFORMS_FILE}")
            self._files[name] = read_transforms(found[name] / TRANSFORMS_FILE)
        return self._files[name]

    # -- classes ---------------------------------------------------------------------------------------------------

    def predicted(self) -> PredictedLabels | None:
        """``labels_from``'s labels.json, read once (None without ``labels_from``); its scene is checked against the
        captures when scenes are listed or loaded (``_check_predicted_scene``), so that the classes can be read
        first (a per-scene model pointed at another capture is refused over its scene, not over these labels)."""
        if self.labels_from is not None and self._predicted is None:
            self._predicted = read_predicted_labels(self.labels_from)
        return self._predicted

    def _check_predicted_scene(self, found: dict[str, Path]) -> None:
        """``labels_from``'s scene must be a capture under ``root``: DataError naming both otherwise."""
        predicted = self.predicted()
        if predicted is not None and predicted.scene not in found:
            raise DataError(f"dataset.labels_from={self.labels_from}: its labels are of scene {predicted.scene!r}, "
                            f"which is no capture under {self.root} (found: {', '.join(found)})")

    def _class_list(self) -> ClassList | None:
        """The one class list of the labelled captures: ``labels_from``'s (the model's), else ``classes_file``, else
        their own or root's classes.json."""
        if self._classes_read:
            return self._classes
        predicted = self.predicted()
        if predicted is not None:
            self._classes, self._classes_read = predicted.classes, True
            return self._classes
        candidates = [self.classes_path] if self.classes_path else [
            *(folder / CLASSES_FILE for folder in self._found().values()), self.root / CLASSES_FILE]
        lists = [read_class_list(path) for path in dict.fromkeys(candidates) if path.is_file()]
        if self.classes_path and not lists:
            raise DataError(f"{self.classes_path}: missing (dataset.classes_file); expected a classes.json")
        for other in lists[1:]:
            if (other.names, other.ignore_index) != (lists[0].names, lists[0].ignore_index):
                raise DataError(f"{other.path}: class list differs from {lists[0].path}; expected one class list for "
                                "every capture of the dataset (or dataset.classes_file)")
        self._classes, self._classes_read = (lists[0] if lists else None), True
        return self._classes

    @property
    def class_names(self) -> tuple[str, ...]:
        """The captures' class list; empty when no capture has one (a model's own list is then used)."""
        classes = self._class_list()
        return classes.names if classes else ()

    @property
    def ignore_index(self) -> int:
        classes = self._class_list()
        return classes.ignore_index if classes else 255

    # -- loading ---------------------------------------------------------------------------------------------------

    def read_scene(self, name: str) -> Scene:
        self._check_predicted_scene(self._found())
        return self._scene(name, self.capture(name))

    def _scene(self, name: str, capture: CaptureFile) -> Scene:
        predicted = self.predicted()
        if predicted is not None and predicted.scene == name:
            return self._predicted_scene(name, capture, predicted)
        return self._scene_of(name, capture)

    def _scene_of(self, name: str, capture: CaptureFile) -> Scene:
        frames = capture.frames
        labelled = [f.semantic is not None for f in frames]
        if any(labelled) and not all(labelled):
            first = frames[labelled.index(False)]
            raise DataError(f"{capture.path}: frame {first.name!r} has no semantic_file_path while others have one; "
                            "expected labels for every frame of a labelled capture, or for none")
        if all(labelled) and self._class_list() is None:
            raise DataError(f"{capture.path}: frames have semantic_file_path but no {CLASSES_FILE} names the classes "
                            f"(beside it, in {self.root} or dataset.classes_file)")
        height, width = self._load_size(frames[0])
        intrinsics = np.stack([scale_intrinsics(f.camera.intrinsics, width / f.camera.width, height / f.camera.height)
                               for f in frames])
        c2w = np.stack([f.c2w for f in frames])
        c2w[:, :3, 3] *= self.scale
        train, held_out = self._split(capture)
        reader = _FrameReader(self, capture, (height, width), intrinsics, c2w)
        if all(labelled) and self.validation != "off":
            reader.check_label_files(sorted(set(train) | set(held_out)))
        near, far = self._depth_bounds(name, capture, reader)
        return Scene(
            name=name, c2w=torch.from_numpy(c2w).float(), intrinsics=torch.from_numpy(intrinsics).float(),
            height=height, width=width, near=near, far=far, train_frames=train, eval_frames=held_out,
            load_frame=reader, labelled=all(labelled),
            sparse_points=functools.partial(read_sparse_points, capture, self.scale) if capture.points else None,
        )

    def _predicted_scene(self, name: str, capture: CaptureFile, predicted: PredictedLabels) -> Scene:
        """The capture with ``labels_from``'s labels: they must be of this capture's frames, at the dataset's size."""
        without = self._scene_unlabelled(name, capture)
        if predicted.frames != without.num_frames or predicted.size != (without.height, without.width):
            raise DataError(f"{predicted.path}: labels of {predicted.frames} frames at {predicted.size[0]}x"
                            f"{predicted.size[1]}, capture {name!r} has {without.num_frames} frames loaded at "
                            f"{without.height}x{without.width}; expected `label` run on this capture at this "
                            "dataset size")
        reader = without.load_frame
        reader.predicted = predicted
        return dataclasses.replace(without, labelled=True)

    def _scene_unlabelled(self, name: str, capture: CaptureFile) -> Scene:
        frames = tuple(dataclasses.replace(f, semantic=None) for f in capture.frames)
        return self._scene_of(name, dataclasses.replace(capture, frames=frames))

    def _load_size(self, first: CaptureFrame) -> tuple[int, int]:
        if self.size != (0, 0):
            return self.size
        h, w = first.camera.height, first.camera.width
        ratio = self.long_side / max(h, w)
        return (max(SIZE_MULTIPLE, round(h * ratio / SIZE_MULTIPLE) * SIZE_MULTIPLE),
                max(SIZE_MULTIPLE, round(w * ratio / SIZE_MULTIPLE) * SIZE_MULTIPLE))

    def _split(self, capture: CaptureFile) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """(training, held-out) frame indices: the file's split lists, else every ``eval_every``-th frame."""
        names = [f.name for f in capture.frames]
        if capture.held_out is not None or capture.train is not None:
            held_out = set(capture.held_out or ())
            train = set(capture.train) if capture.train is not None else set(names) - held_out
            both = sorted(train & held_out)
            if both:
                raise DataError(f"{capture.path}: frame {both[0]!r} is both in train_filenames and in the held-out "
                                "lists; expected disjoint lists")
            return (tuple(i for i, n in enumerate(names) if n in train),
                    tuple(i for i, n in enumerate(names) if n in held_out))
        if not self.eval_every:
            return tuple(range(len(names))), ()
        held = tuple(i for i in range(len(names)) if i % self.eval_every == self.eval_every // 2)
        return tuple(i for i in range(len(names)) if i not in held), held

    def _depth_bounds(self, name: str, capture: CaptureFile, reader: "_FrameReader") -> tuple[float, float]:
        """``dataset.near/far`` if set (checked when the dataset was built); else the capture's own (``_found_bounds``),
        refused unless ``0 < near < far <= MAX_FAR`` (a far like 1e30 in the file would train on nan)."""
        if self.bounds != (0.0, 0.0):
            return self.bounds
        near, far = self._found_bounds(name, capture, reader)
        if not (math.isfinite(near) and math.isfinite(far) and 0 < near < far <= MAX_FAR):
            raise DataError(f"capture {name!r} ({capture.path}): its depth bounds are near={near:g}, far={far:g} m "
                            f"(after dataset.scale={self.scale:g}); expected 0 < near < far <= {MAX_FAR:g} m: fix the "
                            "frames' near/far or depth maps, or set dataset.near and dataset.far")
        return near, far

    def _found_bounds(self, name: str, capture: CaptureFile, reader: "_FrameReader") -> tuple[float, float]:
        """In this order, the frames' bounds from the file, the depth maps' (see ``DEPTH_PERCENTILES``,
        ``DEPTH_MARGIN``), or the sparse points' (``ply_file_path``: each frame's bounds from the points in front of it
        and inside its image, by ``import-colmap``'s rule); metres after ``scale``."""
        frames = capture.frames
        nears = [f.near for f in frames if f.near is not None]
        fars = [f.far for f in frames if f.far is not None]
        if nears and fars:
            return min(nears) * self.scale, max(fars) * self.scale
        with_depth = [i for i, f in enumerate(frames) if f.depth is not None]
        if with_depth:
            picks = [with_depth[round(k * (len(with_depth) - 1) / max(DEPTH_FRAMES - 1, 1))]
                     for k in range(min(DEPTH_FRAMES, len(with_depth)))]
            depths = np.concatenate([reader.depth_of(i).ravel() for i in dict.fromkeys(picks)])
            valid = depths[depths > 0]
            if valid.size:
                low, high = np.percentile(valid, DEPTH_PERCENTILES)
                near = float(low) * (1.0 - DEPTH_MARGIN)
                far = float(high) * (1.0 + DEPTH_MARGIN)
                if near > 0 and far > near:
                    return near, far
        if capture.points is not None:
            bounds = _point_bounds(capture, reader.c2w, reader.intrinsics, reader.size, self.scale)
            if bounds is not None:
                return bounds
        raise DataError(f"capture {name!r} ({capture.path}): no depth bounds (no near/far per frame, no depth maps, no "
                        "ply_file_path points in view); set dataset.near and dataset.far in metres (after "
                        "dataset.scale)")


def _point_cloud(capture: CaptureFile) -> tuple[np.ndarray, np.ndarray]:
    """``(xyz [P, 3] float64, rgb [P, 3] uint8)`` of the capture's sparse points (``ply_file_path``), in the file's
    world, validated (``points.read_point_cloud``)."""
    return read_point_cloud(capture.points)


def read_sparse_points(capture: CaptureFile, scale: float) -> ScenePoints:
    """The capture's sparse points in the poses' world, metres after ``scale`` (``Scene.sparse_points``)."""
    xyz, rgb = _point_cloud(capture)
    xyz = torch.from_numpy((xyz @ capture.world[:3, :3].T + capture.world[:3, 3]) * scale).float()
    check_finite_points(capture.points, xyz.numpy(), " in float32 after the capture's transform and dataset.scale")
    return ScenePoints(xyz=xyz, rgb=torch.from_numpy(rgb).float() / 255.0)


def _point_bounds(capture: CaptureFile, c2w: np.ndarray, intrinsics: np.ndarray, size: tuple[int, int],
                  scale: float) -> tuple[float, float] | None:
    """Scene bounds from the sparse points: per frame, ``import-colmap``'s rule on the depths of the points in front
    of it and inside its image; the smallest near and the largest far. None when no frame sees enough points."""
    from gpnerf_plugins.datasets.capture.colmap_import import depth_bounds

    points, _ = _point_cloud(capture)
    if not len(points):
        return None
    points = (points @ capture.world[:3, :3].T + capture.world[:3, 3]) * scale
    height, width = size
    bounds = []
    for pose, k in zip(c2w, intrinsics):
        camera = (points - pose[:3, 3]) @ pose[:3, :3]  # world -> camera (OpenCV)
        z = camera[:, 2]
        front = z > 1e-9
        pixels = (camera[front, :2] / z[front, None]) * k[[0, 1], [0, 1]] + k[:2, 2]
        inside = (pixels[:, 0] > -0.5) & (pixels[:, 0] < width - 0.5) & (pixels[:, 1] > -0.5) & (pixels[:, 1] < height - 0.5)
        found = depth_bounds(z[front][inside])
        if found is not None:
            bounds.append(found)
    if not bounds:
        return None
    return min(b[0] for b in bounds), max(b[1] for b in bounds)


@dataclass(frozen=True)
class PredictedLabels:
    """What ``python -m gpnerf_core label`` wrote (``dataset.labels_from``): a scene's frames' predicted class ids."""

    path: Path
    scene: str
    frames: int
    size: tuple[int, int]
    classes: ClassList

    def frame_labels(self, index: int) -> np.ndarray:
        """``[H, W]`` int64 class ids of frame ``index``; a missing, damaged or mis-sized file is named."""
        path = self.path / "labels" / f"{index:05d}.png"
        if not path.is_file():
            raise DataError(f"{path}: missing; expected the labels `label` wrote for frame {index} of {self.scene!r}")
        labels = np.asarray(decode_image(path, "a label image"))
        if labels.shape != self.size or not np.issubdtype(labels.dtype, np.integer):
            raise DataError(f"{path}: labels of shape {list(labels.shape)} and type {labels.dtype}; expected "
                            f"{self.size[0]}x{self.size[1]} class ids, as labels.json says")
        labels = labels.astype(np.int64)
        bad = (labels >= len(self.classes.names)) & (labels != self.classes.ignore_index)
        if bad.any():
            raise DataError(f"{path}: class id {int(labels[bad][0])} outside the {len(self.classes.names)} classes "
                            "of labels.json")
        return labels


def read_predicted_labels(folder: Path) -> PredictedLabels:
    """``folder/labels.json`` (``dataset.labels_from``), checked."""
    path = folder / "labels.json"
    if not path.is_file():
        raise DataError(f"dataset.labels_from={folder}: no labels.json in it; expected the folder `python -m "
                        "gpnerf_core label` wrote (its out_dir)")
    try:
        data = json.loads(path.read_text())
        size = (int(data["size"][0]), int(data["size"][1]))
        classes = ClassList(tuple(str(c) for c in data["classes"]), int(data["ignore_index"]), path)
        return PredictedLabels(folder, str(data["scene"]), int(data["frames"]), size, classes)
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise DataError(f"{path}: not a labels.json `label` writes ({type(exc).__name__}: {exc}); expected scene, "
                        "frames, size, classes and ignore_index") from None


def read_class_list(path: Path) -> ClassList:
    """``classes.json``: ``{"classes": [names...], "ignore_index": 255}``."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: not readable JSON ({exc}); expected {{\"classes\": [...], \"ignore_index\": 255}}") \
            from None
    names = data.get("classes") if isinstance(data, dict) else None
    if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
        raise DataError(f"{path}: 'classes' is missing or not a list of names; expected {{\"classes\": [\"wall\", ...], "
                        "\"ignore_index\": 255}")
    ignore = data.get("ignore_index", 255)
    if not isinstance(ignore, int) or isinstance(ignore, bool) or 0 <= ignore < len(names):
        raise DataError(f"{path}: ignore_index={ignore!r}; expected an integer outside the class ids 0..{len(names) - 1}")
    return ClassList(tuple(names), int(ignore), Path(path))


class _FrameReader(FrameDecoder):
    """``Scene.load_frame`` of a capture: decode, undistort, resize, mask and scale one frame (``FrameDecoder``'s
    hooks for a capture's files: any image format, depth in any unit or ``.npy``, lens distortion, masks)."""

    def __init__(self, dataset: CaptureScenes, capture: CaptureFile, size: tuple[int, int], intrinsics: np.ndarray,
                 c2w: np.ndarray) -> None:
        super().__init__(size, dataset.ignore_index)
        self.dataset, self.capture = dataset, capture
        self.intrinsics, self.c2w = intrinsics, c2w
        unit = dataset.depth_unit or capture.depth_unit or DEFAULT_DEPTH_UNIT
        self.depth_scale = unit * dataset.scale
        self._undistorters: dict[tuple, Undistorter] = {}
        self._frames = {frame.name: frame for frame in capture.frames}
        self._index = {frame.name: index for index, frame in enumerate(capture.frames)}
        self.predicted: PredictedLabels | None = None
        """``dataset.labels_from``'s labels, which replace the frames' own (set for the capture they were made of)."""

    def _undistorter(self, frame: CaptureFrame) -> Undistorter | None:
        camera = frame.camera
        if camera.distortion is None:
            return None
        key = (camera.intrinsics.tobytes(), camera.distortion, camera.height, camera.width)
        if key not in self._undistorters:
            self._undistorters[key] = Undistorter(camera.intrinsics, camera.distortion, camera.height, camera.width)
        return self._undistorters[key]

    def _stored(self, path: Path, frame: CaptureFrame, what: str) -> np.ndarray:
        """A frame's image file as an array, checked to have the colour image's size."""
        if path.suffix.lower() == ".npy":
            try:
                array = np.load(path, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise DataError(f"{path}: unreadable {what} ({exc}); expected a 2-D .npy array") from None
        else:
            array = np.asarray(decode_image(path, f"a {what} image"))
        if array.shape[:2] != (frame.camera.height, frame.camera.width):
            raise DataError(f"{path}: {what} is {array.shape[1]}x{array.shape[0]}, the image "
                            f"{frame.camera.width}x{frame.camera.height}; expected the same size")
        return array

    @staticmethod
    def files(frame: CaptureFrame) -> FrameFiles:
        return FrameFiles(frame.image, frame.depth, frame.semantic, None, frame.mask, name=frame.name)

    def rgb(self, files: FrameFiles) -> np.ndarray:
        frame = self._frames[files.name]
        image = decode_image(files.rgb, "an image (PNG or JPEG)")
        rgb = np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0
        undistort = self._undistorter(frame)
        if undistort is not None:
            rgb = undistort.rgb(rgb)
        return resize_rgb(rgb, *self.size)

    def depth_of(self, index: int) -> np.ndarray:
        """Frame ``index``'s depth (``depth``); the scene's depth bounds read it."""
        return self.depth(self.files(self.capture.frames[index]))

    def depth(self, files: FrameFiles) -> np.ndarray:
        """``[H, W]`` float32 metres (after ``scale``) at the dataset's size, 0 where unknown."""
        frame = self._frames[files.name]
        if files.depth is None:
            return np.zeros(self.size, dtype=np.float32)
        stored = self._stored(files.depth, frame, "depth")
        if stored.ndim != 2 or not (np.issubdtype(stored.dtype, np.integer) or np.issubdtype(stored.dtype, np.floating)):
            raise DataError(f"{files.depth}: depth of shape {list(stored.shape)} and type {stored.dtype}; expected a "
                            "single-channel 16-bit PNG or a 2-D .npy")
        if stored.dtype == np.uint8:
            raise DataError(f"{files.depth}: depth stored in 8 bits (at most 255 units); expected a 16-bit PNG or a "
                            ".npy of depths")
        depth = stored.astype(np.float32) * np.float32(self.depth_scale)
        if not np.isfinite(depth).all() or (depth < 0).any():
            raise DataError(f"{files.depth}: depth negative or not finite; expected depths >= 0 (0 = unknown)")
        undistort = self._undistorter(frame)
        if undistort is not None:
            depth = undistort.values(depth)
        return resize_nearest(depth, *self.size).astype(np.float32)

    def labels(self, files: FrameFiles) -> np.ndarray:
        frame = self._frames[files.name]
        if self.predicted is not None:
            return self.predicted.frame_labels(self._index[files.name])
        if files.semantic is None:
            return np.full(self.size, self.ignore_index, dtype=np.int64)
        stored = self._stored(files.semantic, frame, "semantic label")
        if stored.ndim != 2 or not np.issubdtype(stored.dtype, np.integer):
            raise DataError(f"{files.semantic}: labels of shape {list(stored.shape)} and type {stored.dtype}; "
                            "expected a single-channel 8- or 16-bit PNG of class ids")
        labels = stored.astype(np.int64)
        self._check_class_ids(files.semantic, labels)
        undistort = self._undistorter(frame)
        if undistort is not None:
            labels = undistort.labels(labels, self.ignore_index)
        return resize_nearest(labels, *self.size)

    def check_label_files(self, indices: Sequence[int]) -> None:
        """The class ids of frames ``indices``' label files, read when the scene loads (``dataset.validate`` quick or
        full), so an id outside the class list in a frame the quick check decodes no further is refused, naming the
        file, before training rather than when training or evaluation first reads that frame."""
        for index in indices:
            frame = self.capture.frames[index]
            stored = self._stored(frame.semantic, frame, "semantic label")
            if stored.ndim == 2 and np.issubdtype(stored.dtype, np.integer):  # else labels() names the file's type
                self._check_class_ids(frame.semantic, stored.astype(np.int64))

    def _check_class_ids(self, path: Path, labels: np.ndarray) -> None:
        """Every id of the label file ``path`` is a class of the class list or its ignore index, named with the file
        where one is not (read when the frame is: before training for a training frame, see ``CaptureScenes``)."""
        classes = self.dataset._class_list()
        if classes is None:
            return
        bad = ((labels < 0) | (labels >= len(classes.names))) & (labels != classes.ignore_index)
        if bad.any():
            found = np.unique(labels[bad])
            raise DataError(f"{path}: class id {int(found[0])} outside the {len(classes.names)} classes 0.."
                            f"{len(classes.names) - 1} of {classes.path} and not its ignore_index={classes.ignore_index}"
                            f" ({len(found)} such id{'s' if len(found) > 1 else ''}, {int(bad.sum())} pixels); expected "
                            "class ids of that list (fix the file, or the class list)")

    def keep(self, files: FrameFiles) -> np.ndarray | None:
        if files.mask is None:
            return None
        frame = self._frames[files.name]
        mask = self._stored(files.mask, frame, "mask")
        mask = (mask if mask.ndim == 2 else mask[..., 0]).astype(np.float32)
        undistort = self._undistorter(frame)
        if undistort is not None:
            mask = undistort.values(mask)
        return resize_nearest(mask, *self.size) > 0

    def __call__(self, index: int) -> Frame:
        return self.decode(self.files(self.capture.frames[index]), torch.from_numpy(self.intrinsics[index]).float(),
                           torch.from_numpy(self.c2w[index]).float())


__all__ = ["CaptureScenes", "CaptureScenesConfig", "read_class_list"]
