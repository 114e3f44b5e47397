"""Reader of one sequence in the Replica (Semantic-NeRF render) layout.

A sequence folder holds::

    rgb/rgb_<i>.png                          uint8 RGB(A)
    depth/depth_<i>.png                      uint16, millimetres (0 = unknown)
    semantic_class/semantic_class_<i>.png    raw class ids (optional with ``require_semantic=False``)
    semantic_instance/semantic_instance_<i>.png   optional, instance ids (0 = background)
    traj_w_c.txt                             one row of 16 numbers per frame: row-major 4x4 camera-to-world,
                                             OpenCV convention, metres

Frames are ordered by the integer ``i`` and the k-th pose row belongs to the k-th frame. Intrinsics follow the
Semantic-NeRF camera: a horizontal field of view (90 degrees) at the loaded resolution, square pixels and a
centred principal point with pixel centres at integers.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence, Union

import numpy as np
import torch

from gpnerf_core import EXPECTED_RIGID, ConfigError, DataError, Frame, Scene, check_depth_range, rigid_transform_problem
from gpnerf_plugins.datasets.common.decoding import FrameDecoder, FrameFiles
from gpnerf_plugins.datasets.common.image_io import check_depth_mode, image_header, image_size

TRAJECTORY_FILE = "traj_w_c.txt"
RGB_DIR, DEPTH_DIR, CLASS_DIR, INSTANCE_DIR = "rgb", "depth", "semantic_class", "semantic_instance"

SplitRule = Callable[[int], tuple[Sequence[int], Sequence[int]]]
"""``num_frames -> (train_frames, eval_frames)``."""
FrameSplit = Union[tuple[Sequence[int], Sequence[int]], SplitRule, None]


def frame_file_pattern(prefix: str) -> re.Pattern[str]:
    """``<prefix>_<token>.png``; group 1 is the token (a frame number in a valid folder)."""
    return re.compile(rf"^{re.escape(prefix)}_(.+)\.png$")


def every_nth_split(num_frames: int, every: int, offset: int | None = None) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Hold out every ``every``-th frame for evaluation.

    Args:
        num_frames: frames in the sequence.
        every: period of held-out frames; 0 holds out nothing.
        offset: index of the first held-out frame (default ``every // 2``, so each held-out frame sits in the
            middle of a run of training frames).

    Returns:
        ``(train_frames, eval_frames)``, disjoint and ascending.
    """
    if every < 0:
        raise ConfigError(f"eval_every={every} is negative; expected 0 (no held-out frames) or a period >= 2")
    if every == 0:
        return tuple(range(num_frames)), ()
    if every == 1:
        raise ConfigError("eval_every=1 would hold out every frame; expected 0 or a period >= 2")
    start = every // 2 if offset is None else offset
    held = set(range(start, num_frames, every))
    return tuple(i for i in range(num_frames) if i not in held), tuple(sorted(held))


def hfov_intrinsics(height: int, width: int, hfov_deg: float, aspect_scale: float = 1.0) -> np.ndarray:
    """Pinhole matrix ``[3, 3]`` of a camera with horizontal field of view ``hfov_deg`` at ``height`` x ``width``.

    ``fx = W / (2 tan(hfov / 2))``, ``fy = fx * aspect_scale`` (1 unless a resize changed the aspect ratio),
    ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2``.
    """
    fx = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    return np.array(
        [[fx, 0.0, (width - 1) / 2.0], [0.0, fx * aspect_scale, (height - 1) / 2.0], [0.0, 0.0, 1.0]],
        dtype=np.float64,
    )


@dataclass(frozen=True)
class SequenceFrame:
    """Files of one frame; ``number`` is the ``i`` of ``rgb_<i>.png``; None for a kind the sequence lacks."""

    number: int
    rgb: Path
    depth: Path
    semantic: Path | None
    instance: Path | None


class ReplicaFrames(FrameDecoder):
    """The Replica layout's frames: ``FrameDecoder``'s PNGs, raw class ids mapped through ``label_map`` (raw ids past
    its end become the ignore index; None keeps raw ids)."""

    def __init__(self, size: tuple[int, int], ignore_index: int, label_map: np.ndarray | None) -> None:
        super().__init__(size, ignore_index)
        self.label_map = label_map

    def class_ids(self, stored: np.ndarray, files: FrameFiles) -> np.ndarray:
        if self.label_map is None:
            return stored
        out = np.full(stored.shape, self.ignore_index, dtype=np.int64)
        known = (stored >= 0) & (stored < len(self.label_map))
        out[known] = self.label_map[stored[known]]
        return out


def read_trajectory(path: Path) -> np.ndarray:
    """Parse ``traj_w_c.txt`` into ``[N, 4, 4]`` float64 camera-to-world matrices."""
    if not path.is_file():
        raise DataError(f"{path}: missing; expected one row of 16 numbers (row-major 4x4 camera-to-world) per frame")
    poses = []
    for line_no, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        fields = line.split()
        try:
            values = [float(v) for v in fields]
        except ValueError:
            raise DataError(f"{path}:{line_no}: non-numeric value in {line.strip()[:60]!r}; expected 16 numbers") from None
        if len(values) != 16:
            raise DataError(f"{path}:{line_no}: {len(values)} numbers; expected 16 (row-major 4x4 camera-to-world)")
        pose = np.asarray(values, dtype=np.float64).reshape(4, 4)
        problem = rigid_transform_problem(pose)
        if problem is not None:
            raise DataError(f"{path}:{line_no}: camera-to-world pose has {problem}; expected {EXPECTED_RIGID}")
        poses.append(pose)
    if not poses:
        raise DataError(f"{path}: no poses; expected one row of 16 numbers per frame")
    return np.stack(poses)


def _list_frames(root: Path, require_semantic: bool, require_instance: bool) -> list[SequenceFrame]:
    """Frames in numeric order; every rgb frame needs a file of each kind that is required or has a folder."""
    rgb_dir = root / RGB_DIR
    if not rgb_dir.is_dir():
        raise DataError(f"{rgb_dir}: missing; expected a folder of rgb_<i>.png frames")
    has_semantic = require_semantic or (root / CLASS_DIR).is_dir()
    has_instance = require_instance or (root / INSTANCE_DIR).is_dir()
    pattern = frame_file_pattern("rgb")
    frames = []
    for path in rgb_dir.iterdir():
        match = pattern.match(path.name)
        if match is None:
            continue
        token = match.group(1)
        if not token.isdigit():
            raise DataError(f"{path}: frame name {token!r} is not a number; expected rgb_<i>.png with integer i")
        depth = root / DEPTH_DIR / f"depth_{token}.png"
        semantic = root / CLASS_DIR / f"semantic_class_{token}.png" if has_semantic else None
        instance = root / INSTANCE_DIR / f"semantic_instance_{token}.png" if has_instance else None
        for companion in (depth, semantic, instance):
            if companion is not None and not companion.is_file():
                raise DataError(f"{companion}: missing; expected it beside {path.name} (every rgb frame needs one)")
        frames.append(SequenceFrame(int(token), path, depth, semantic, instance))
    if not frames:
        raise DataError(f"{rgb_dir}: no rgb_<i>.png frames")
    frames.sort(key=lambda f: f.number)
    for a, b in zip(frames, frames[1:]):
        if a.number == b.number:
            raise DataError(f"{b.rgb}: frame number {b.number} also used by {a.rgb.name}; expected unique numbers")
    return frames


class ReplicaSequence:
    """One Replica-layout sequence: file index and poses parsed eagerly, images decoded per frame.

    Args:
        path: the sequence folder (``.../office_0/Sequence_1``).
        hfov_deg: horizontal field of view of the renders, degrees.
        size: ``(H, W)`` to load frames at, or None for the files' size. RGB is resized with antialiasing,
            depth and labels with nearest neighbour; intrinsics are derived at the loaded size.
        label_map: int array, ``label_map[raw_id]`` is the class id; raw ids past its end, and entries equal to
            ``ignore_index``, become ``ignore_index``. None keeps raw ids.
        ignore_index: label value of unlabelled pixels.
        require_semantic: every frame needs a ``semantic_class`` file; False makes the folder optional (without
            it ``Frame.semantic`` is all ``ignore_index``).
        require_instance: every frame needs a ``semantic_instance`` file; False makes the folder optional (without
            it ``Frame.instance`` is None).

    Raises:
        DataError: a missing or malformed file, named in the message.
    """

    folder_kind = "sequence"
    """How errors name ``path``."""

    def __init__(
        self,
        path: str | Path,
        *,
        hfov_deg: float = 90.0,
        size: tuple[int, int] | None = None,
        label_map: np.ndarray | Sequence[int] | None = None,
        ignore_index: int = 255,
        require_semantic: bool = True,
        require_instance: bool = False,
    ) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            folders = [RGB_DIR, DEPTH_DIR] + [CLASS_DIR] * require_semantic + [INSTANCE_DIR] * require_instance
            raise DataError(
                f"{self.path}: {self.folder_kind} folder missing; "
                f"expected {', '.join(f'{folder}/' for folder in folders)} and {TRAJECTORY_FILE}"
            )
        if not 0.0 < hfov_deg < 180.0:
            raise ConfigError(f"hfov_deg={hfov_deg}; expected a field of view in (0, 180) degrees")
        self.ignore_index = int(ignore_index)
        self.label_map = None if label_map is None else np.asarray(label_map, dtype=np.int64)
        if self.label_map is not None and self.label_map.ndim != 1:
            raise ConfigError(f"label_map has shape {self.label_map.shape}; expected a 1-D array raw id -> class id")
        self.files = _list_frames(self.path, require_semantic, require_instance)
        poses = read_trajectory(self.path / TRAJECTORY_FILE)
        if len(poses) != len(self.files):
            raise DataError(
                f"{self.path / TRAJECTORY_FILE}: {len(poses)} poses for {len(self.files)} rgb frames; "
                "expected one pose per frame"
            )
        self.native_size = self._check_sizes()
        if size is not None and (len(size) != 2 or min(size) < 1):
            raise ConfigError(f"size={size}; expected (height, width) with positive integers")
        self.height, self.width = (int(size[0]), int(size[1])) if size is not None else self.native_size
        aspect_scale = (self.height / self.native_size[0]) / (self.width / self.native_size[1])
        self.intrinsics = torch.from_numpy(hfov_intrinsics(self.height, self.width, hfov_deg, aspect_scale)).float()
        self.c2w = torch.from_numpy(poses).float()
        self.decoder = ReplicaFrames((self.height, self.width), self.ignore_index, self.label_map)

    @property
    def num_frames(self) -> int:
        return len(self.files)

    def _check_sizes(self) -> tuple[int, int]:
        """The frames' common ``(H, W)``, from every file's header; a depth PNG's header must also say 16 bits (an
        8-bit depth map is refused here, before training, at the cost of the header read that is done anyway)."""
        expected = image_size(self.files[0].rgb)
        for frame in self.files:
            for path in (frame.rgb, frame.depth, frame.semantic, frame.instance):
                if path is None:
                    continue
                found, mode = image_header(path)
                if path is frame.depth:
                    check_depth_mode(path, mode)
                if found != expected:
                    raise DataError(
                        f"{path}: image is {found[0]}x{found[1]} (HxW); "
                        f"expected {expected[0]}x{expected[1]} like {self.files[0].rgb.name}"
                    )
        return expected

    def load_frame(self, index: int) -> Frame:
        """Decode frame ``index`` (position in the numeric order) at the loaded size."""
        if not 0 <= index < self.num_frames:
            raise DataError(f"{self.path}: frame index {index} out of range; expected 0..{self.num_frames - 1}")
        files = self.files[index]
        decoded = FrameFiles(files.rgb, files.depth, files.semantic, files.instance, name=str(files.number))
        return self.decoder.decode(decoded, self.intrinsics.clone(), self.c2w[index].clone())

    def scene(
        self,
        *,
        name: str | None = None,
        split: FrameSplit = None,
        near: float = 0.1,
        far: float = 10.0,
        allow_overlap: bool = False,
    ) -> Scene:
        """Wrap the sequence as a ``Scene``.

        Args:
            name: scene name; default ``<parent folder>/<sequence folder>``.
            split: ``(train_frames, eval_frames)`` index lists, or a rule ``num_frames -> (train, eval)`` such as
                ``functools.partial(every_nth_split, every=20)``; None trains on every frame.
            near, far: ray-sampling depth bounds in metres.
            allow_overlap: accept frames in both lists (only for a paper-parity protocol); else a ConfigError.
        """
        if split is None:
            train, held = tuple(range(self.num_frames)), ()
        elif callable(split):
            train, held = split(self.num_frames)
        else:
            train, held = split
        train, held = tuple(int(i) for i in train), tuple(int(i) for i in held)
        for label, indices in (("train_frames", train), ("eval_frames", held)):
            bad = [i for i in indices if not 0 <= i < self.num_frames]
            if bad:
                raise ConfigError(f"{label} of {self.path} has index {bad[0]}; expected 0..{self.num_frames - 1}")
        overlap = sorted(set(train) & set(held))
        if overlap and not allow_overlap:
            raise ConfigError(
                f"frame {overlap[0]} of {self.path} is in both train_frames and eval_frames; expected disjoint lists"
            )
        near, far = check_depth_range(near, far)
        n = self.num_frames
        return Scene(
            name=name if name is not None else f"{self.path.parent.name}/{self.path.name}",
            c2w=self.c2w.clone(),
            intrinsics=self.intrinsics.expand(n, 3, 3).clone(),
            height=self.height,
            width=self.width,
            near=float(near),
            far=float(far),
            train_frames=train,
            eval_frames=held,
            load_frame=self.load_frame,
        )


def read_replica_sequence(
    path: str | Path,
    *,
    name: str | None = None,
    split: FrameSplit = None,
    near: float = 0.1,
    far: float = 10.0,
    hfov_deg: float = 90.0,
    size: tuple[int, int] | None = None,
    label_map: np.ndarray | Sequence[int] | None = None,
    ignore_index: int = 255,
) -> Scene:
    """Read one Replica-layout sequence as a ``Scene``; see ``ReplicaSequence`` and ``ReplicaSequence.scene``."""
    sequence = ReplicaSequence(path, hfov_deg=hfov_deg, size=size, label_map=label_map, ignore_index=ignore_index)
    return sequence.scene(name=name, split=split, near=near, far=far)
