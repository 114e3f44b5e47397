"""Reader of one scene in the DM-NeRF Replica layout (GP-NeRF's "Replica_DM"), plus PNG helpers.

A scene folder holds (no ``Sequence_<n>`` level)::

    rgb/rgb_<i>.png                              uint8 RGB(A)
    depth/depth_<i>.png                          uint16, millimetres (0 = unknown)
    semantic_instance/semantic_instance_<i>.png  raw instance ids, kept as they are
    semantic_class/semantic_class_<i>.png        optional: raw Replica class ids
    traj_w_c.txt                                 one row of 16 numbers per frame: row-major 4x4 camera-to-world,
                                                 OpenCV convention, metres

Frames are numbered ``i = 0 .. N-1`` with N the number of poses, and pose row ``i`` belongs to frame ``i``
(the reference builds the file names from ``range(N)``). The camera is Semantic-NeRF's (90 degree horizontal field
of view, centred principal point), derived at the loaded resolution.

``replica_layout.ReplicaSequence`` reads the Semantic-NeRF layout, whose ``semantic_class`` folder is mandatory;
this layout usually has none, hence a reader of its own.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from skimage import io as skio
from skimage.transform import resize as sk_resize

from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.types import Frame, Scene
from gpnerf_plugins.datasets.replica_classes import IGNORE_INDEX, map_raw_labels
from gpnerf_plugins.datasets.replica_layout import (
    CLASS_DIR,
    DEPTH_DIR,
    DEPTH_SCALE,
    INSTANCE_DIR,
    RGB_DIR,
    TRAJECTORY_FILE,
    hfov_intrinsics,
    read_trajectory,
)


def frame_file_pattern(prefix: str) -> re.Pattern[str]:
    """``<prefix>_<token>.png``; group 1 is the token (a frame number in a valid folder)."""
    return re.compile(rf"^{re.escape(prefix)}_(.+)\.png$")


def one_line_error(exc: Exception) -> str:
    """``Type: first line of the message`` (some decoders raise multi-line messages)."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".rstrip(": ")


def png_size(path: Path) -> tuple[int, int]:
    """``(H, W)`` from the image header, without decoding."""
    try:
        with Image.open(path) as image:
            width, height = image.size
    except Exception as exc:
        raise DataError(f"{path}: unreadable image ({one_line_error(exc)}); expected a PNG") from None
    return height, width


def read_png(path: Path) -> np.ndarray:
    """Decode a PNG to an array with its stored dtype (uint8 or uint16); one-line DataError if it can't."""
    try:
        return np.asarray(skio.imread(path))
    except Exception as exc:
        raise DataError(f"{path}: unreadable image ({one_line_error(exc)}); expected a PNG") from None


def read_index_png(path: Path, what: str) -> np.ndarray:
    """A single-channel integer PNG (depth or ids) as int64 ``[H, W]``."""
    image = read_png(path)
    if image.ndim != 2 or not np.issubdtype(image.dtype, np.integer):
        raise DataError(
            f"{path}: {image.dtype} image of shape {image.shape}; expected a single-channel integer PNG of {what}"
        )
    return image.astype(np.int64)


def read_rgb_png(path: Path) -> np.ndarray:
    """An 8-bit RGB(A) PNG as float32 ``[H, W, 3]`` in [0, 1]."""
    image = read_png(path)
    if image.ndim != 3 or image.shape[2] not in (3, 4) or image.dtype != np.uint8:
        raise DataError(f"{path}: {image.dtype} image of shape {image.shape}; expected 8-bit RGB or RGBA")
    return image[..., :3].astype(np.float32) / 255.0


def resize_nearest(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour resize sampling the source pixel under each destination pixel centre."""
    if image.shape[:2] == (height, width):
        return image
    rows = np.minimum(((np.arange(height) + 0.5) * image.shape[0] / height).astype(np.int64), image.shape[0] - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * image.shape[1] / width).astype(np.int64), image.shape[1] - 1)
    return image[rows[:, None], cols[None, :]]


def resize_rgb(rgb: np.ndarray, height: int, width: int) -> np.ndarray:
    """Antialiased bilinear resize of ``[H, W, 3]`` float RGB, as ``ReplicaSequence`` does."""
    if rgb.shape[:2] == (height, width):
        return rgb
    out = sk_resize(rgb, (height, width), order=1, anti_aliasing=True, preserve_range=True)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class InstanceFrameFiles:
    """Files of frame ``number``; ``semantic`` is None when the scene has no ``semantic_class`` folder."""

    number: int
    rgb: Path
    depth: Path
    instance: Path
    semantic: Path | None


def _list_frames(root: Path, num_poses: int) -> list[InstanceFrameFiles]:
    rgb_dir = root / RGB_DIR
    if not rgb_dir.is_dir():
        raise DataError(f"{rgb_dir}: missing; expected a folder of rgb_<i>.png frames")
    pattern = frame_file_pattern("rgb")
    tokens: dict[int, str] = {}
    for path in sorted(rgb_dir.iterdir()):
        match = pattern.match(path.name)
        if match is None:
            continue
        token = match.group(1)
        if not token.isdigit():
            raise DataError(f"{path}: frame name {token!r} is not a number; expected rgb_<i>.png with integer i")
        if int(token) in tokens:
            other = f"rgb_{tokens[int(token)]}.png"
            raise DataError(f"{path}: frame number {int(token)} also used by {other}; expected unique numbers")
        tokens[int(token)] = token
    if len(tokens) != num_poses:
        raise DataError(
            f"{root / TRAJECTORY_FILE}: {num_poses} poses for {len(tokens)} rgb frames; expected one pose per frame"
        )
    has_semantic = (root / CLASS_DIR).is_dir()
    frames = []
    for number in range(num_poses):
        if number not in tokens:
            missing = rgb_dir / f"rgb_{number}.png"
            raise DataError(f"{missing}: missing; expected frames numbered 0..{num_poses - 1}, one per pose")
        token = tokens[number]
        files = InstanceFrameFiles(
            number=number,
            rgb=rgb_dir / f"rgb_{token}.png",
            depth=root / DEPTH_DIR / f"depth_{token}.png",
            instance=root / INSTANCE_DIR / f"semantic_instance_{token}.png",
            semantic=root / CLASS_DIR / f"semantic_class_{token}.png" if has_semantic else None,
        )
        for companion in (files.depth, files.instance, files.semantic):
            if companion is not None and not companion.is_file():
                raise DataError(
                    f"{companion}: missing; expected it beside {files.rgb.name} (every rgb frame needs one)"
                )
        frames.append(files)
    return frames


class InstanceSequence:
    """One DM-NeRF-layout scene: file index and poses parsed eagerly, images decoded per frame.

    Args:
        path: the scene folder (``.../office_0``).
        hfov_deg: horizontal field of view of the renders, degrees.
        size: ``(H, W)`` to load frames at, or None for the files' size. RGB is resized with antialiasing, depth and
            ids with nearest neighbour; intrinsics are derived at the loaded size.
        strict_labels: raw class ids above 101 in ``semantic_class`` raise DataError (else they become ignore).

    Raises:
        DataError: a missing or malformed file, named in the message.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        hfov_deg: float = 90.0,
        size: tuple[int, int] | None = None,
        strict_labels: bool = True,
    ) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise DataError(
                f"{self.path}: scene folder missing; expected rgb/, depth/, semantic_instance/ and {TRAJECTORY_FILE}"
            )
        if not 0.0 < hfov_deg < 180.0:
            raise ConfigError(f"hfov_deg={hfov_deg}; expected a field of view in (0, 180) degrees")
        self.strict_labels = strict_labels
        poses = read_trajectory(self.path / TRAJECTORY_FILE)
        self.files = _list_frames(self.path, len(poses))
        self.native_size = self._check_sizes()
        if size is not None and (len(size) != 2 or min(size) < 1):
            raise ConfigError(f"size={size}; expected (height, width) with positive integers")
        self.height, self.width = (int(size[0]), int(size[1])) if size is not None else self.native_size
        aspect_scale = (self.height / self.native_size[0]) / (self.width / self.native_size[1])
        self.intrinsics = torch.from_numpy(hfov_intrinsics(self.height, self.width, hfov_deg, aspect_scale)).float()
        self.c2w = torch.from_numpy(poses).float()

    @property
    def num_frames(self) -> int:
        return len(self.files)

    @property
    def has_semantic(self) -> bool:
        return self.files[0].semantic is not None

    def _check_sizes(self) -> tuple[int, int]:
        expected = png_size(self.files[0].rgb)
        for frame in self.files:
            for path in (frame.rgb, frame.depth, frame.instance, frame.semantic):
                if path is None:
                    continue
                found = png_size(path)
                if found != expected:
                    raise DataError(
                        f"{path}: image is {found[0]}x{found[1]} (HxW); "
                        f"expected {expected[0]}x{expected[1]} like {self.files[0].rgb.name}"
                    )
        return expected

    def load_frame(self, index: int) -> Frame:
        """Decode frame ``index`` at the loaded size; ``semantic`` is all ``IGNORE_INDEX`` without class labels."""
        if not 0 <= index < self.num_frames:
            raise DataError(f"{self.path}: frame index {index} out of range; expected 0..{self.num_frames - 1}")
        files = self.files[index]
        h, w = self.height, self.width
        rgb = resize_rgb(read_rgb_png(files.rgb), h, w)
        depth = resize_nearest(read_index_png(files.depth, "depth in millimetres"), h, w)
        depth = depth.astype(np.float32) / DEPTH_SCALE
        instance = resize_nearest(read_index_png(files.instance, "instance ids"), h, w)
        if files.semantic is None:
            semantic = torch.full((h, w), IGNORE_INDEX, dtype=torch.int64)
        else:
            raw = resize_nearest(read_index_png(files.semantic, "class ids"), h, w)
            raw = torch.from_numpy(np.ascontiguousarray(raw))
            semantic = map_raw_labels(raw, files.semantic, strict=self.strict_labels)
        return Frame(
            rgb=torch.from_numpy(np.ascontiguousarray(rgb)),
            depth=torch.from_numpy(np.ascontiguousarray(depth)),
            semantic=semantic,
            intrinsics=self.intrinsics.clone(),
            c2w=self.c2w[index].clone(),
            instance=torch.from_numpy(np.ascontiguousarray(instance)),
        )

    def scene(
        self, *, name: str, train_frames: tuple[int, ...], eval_frames: tuple[int, ...], near: float, far: float
    ) -> Scene:
        """Wrap the scene; ``train_frames`` and ``eval_frames`` may overlap only for a paper-parity protocol."""
        n = self.num_frames
        for label, indices in (("train_frames", train_frames), ("eval_frames", eval_frames)):
            bad = [i for i in indices if not 0 <= i < n]
            if bad:
                raise ConfigError(f"{label} of {self.path} has index {bad[0]}; expected 0..{n - 1}")
        if not 0.0 < near < far:
            raise ConfigError(f"near={near}, far={far}; expected 0 < near < far (metres)")
        return Scene(
            name=name,
            c2w=self.c2w.clone(),
            intrinsics=self.intrinsics.expand(n, 3, 3).clone(),
            height=self.height,
            width=self.width,
            near=float(near),
            far=float(far),
            train_frames=tuple(train_frames),
            eval_frames=tuple(eval_frames),
            load_frame=self.load_frame,
        )
