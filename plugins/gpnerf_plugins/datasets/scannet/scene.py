"""One ScanNet scene folder (Semantic-Ray export layout) as a ``Scene``, and the per-scene frame protocols.

Frames are indexed in NUMERIC order of their names after dropping frames with an invalid pose. Colour is resized
with antialiasing (PIL bilinear, area-aligned), labels and instance ids (``instance-filt/``, when the scene has it)
with nearest neighbour, and the colour intrinsics are scaled by the true ratios ``width / W_color`` and
``height / H_color``. Instance ids are kept as stored: 0 (not annotated) is one id like any other, the background of
the instance protocol.

Depth comes from its own camera: ScanNet's depth images (640x480) have their own intrinsics
(``intrinsic/intrinsic_depth.txt``), not the colour camera's scaled down. ``depth_alignment="intrinsics"`` (default)
registers depth to the colour camera: every output pixel's ray ``K_color^-1 [u, v, 1]`` is projected with ``K_depth``
and the nearest depth pixel taken (0 = unknown where it falls outside the depth image). The two cameras share their
centre and orientation (ScanNet's colour-to-depth extrinsics are the identity), so the depth value, a z, carries over
unchanged. ``"resize"`` is the reference's behaviour: the depth image resized to the output size as if it had the
colour intrinsics (about 1.5 px vertical offset at 320x240 on real scans).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from PIL import Image

from gpnerf_core import ConfigError, Frame, Scene, check_depth_range
from gpnerf_plugins.datasets.common.cameras import scale_intrinsics
from gpnerf_plugins.datasets.common.decoding import FrameDecoder
from gpnerf_plugins.datasets.common.decoding import FrameFiles as DecodedFiles
from gpnerf_plugins.datasets.common.image_io import resize_nearest
from gpnerf_plugins.datasets.scannet.files import (
    DEPTH_SCALE,
    INTRINSIC_COLOR,
    INTRINSIC_DEPTH,
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
from gpnerf_plugins.datasets.scannet.labels import IGNORE_INDEX, LabelMap

PROTOCOLS = ("heldout", "paper_parity")
DEPTH_ALIGNMENTS = ("intrinsics", "resize")


def depth_lookup(k_color: np.ndarray, k_depth: np.ndarray, height: int, width: int, depth_hw: tuple[int, int]):
    """Nearest depth pixel of every output pixel: ``(rows, cols, inside)`` arrays ``[height, width]``.

    ``k_color``: colour intrinsics at the output size; ``k_depth``: depth intrinsics at the depth image's size.
    Pixel centres are at integer coordinates in both.
    """
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(k_color).T  # [H, W, 3], z = 1
    projected = rays @ k_depth.T
    cols = np.rint(projected[..., 0] / projected[..., 2]).astype(np.int64)
    rows = np.rint(projected[..., 1] / projected[..., 2]).astype(np.int64)
    inside = (rows >= 0) & (rows < depth_hw[0]) & (cols >= 0) & (cols < depth_hw[1])
    return np.clip(rows, 0, depth_hw[0] - 1), np.clip(cols, 0, depth_hw[1] - 1), inside
EVAL_POSITIONS = slice(2, 700, 20)
"""Positions (in the scene's frame list) of the evaluation targets, capped at ``NUM_EVAL_FRAMES``: 2, 22, ..., 182."""
NUM_EVAL_FRAMES = 10
FINETUNE_POSITIONS = slice(0, 700, 3)
"""The reference's fine-tuning targets (``paper_parity`` only); they include eval positions 42, 102 and 162."""


def frame_split(tokens: Sequence[str], protocol: str) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Train and eval frame indices of a scene.

    Args:
        tokens: frame names in the scene's (numeric) frame order, invalid-pose frames already dropped.
        protocol: ``heldout``: eval = positions ``[2:700:20][:10]`` of the numeric order, train = every other frame
            (disjoint). ``paper_parity``: the same positions taken in the LEXICOGRAPHIC order of the names
            ("0", "1", "10", "100", ...) as the reference does, and train = lexicographic positions ``[0:700:3]``,
            which overlap the eval frames (the reference's fine-tuning leak, kept for parity only).

    Returns:
        ``(train_frames, eval_frames)``, each ascending, as indices into ``tokens``.
    """
    n = len(tokens)
    if protocol == "heldout":
        held = list(range(n))[EVAL_POSITIONS][:NUM_EVAL_FRAMES]
        held_set = set(held)
        return tuple(i for i in range(n) if i not in held_set), tuple(held)
    if protocol == "paper_parity":
        lexicographic = sorted(range(n), key=lambda i: tokens[i])
        held = sorted(lexicographic[EVAL_POSITIONS][:NUM_EVAL_FRAMES])
        return tuple(sorted(lexicographic[FINETUNE_POSITIONS])), tuple(held)
    raise ConfigError(f"dataset.protocol={protocol!r}; expected one of: {', '.join(PROTOCOLS)}")


class ScanNetScene:
    """A scene folder: frame index, poses and intrinsics read eagerly; images decoded per ``load_frame``.

    Args:
        path: the ``sceneXXXX_YY`` folder.
        label_map: raw id -> ScanNet-20 class.
        height, width: size frames are loaded at, pixels.
        depth_alignment: ``intrinsics`` (register depth with ``intrinsic_depth.txt``) or ``resize`` (the reference's);
            see the module docstring. Without ``intrinsic_depth.txt``, ``intrinsics`` warns once and resizes.

    Raises:
        DataError: a missing or malformed file (the first one found), or no frame with a valid pose.
    """

    def __init__(
        self, path: str | Path, *, label_map: LabelMap, height: int, width: int, depth_alignment: str = "intrinsics"
    ) -> None:
        if depth_alignment not in DEPTH_ALIGNMENTS:
            raise ConfigError(
                f"dataset.depth_alignment={depth_alignment!r}; expected one of: {', '.join(DEPTH_ALIGNMENTS)}"
            )
        self.path = Path(path)
        if not self.path.is_dir():
            expected = "a scene folder with color/, depth/, label-filt/, pose/ and intrinsic/"
            raise LayoutError(self.path, expected, "nothing")
        if height < 1 or width < 1:
            raise ConfigError(f"dataset.height={height}, dataset.width={width}; expected positive sizes in pixels")
        self.label_map = label_map
        self.height, self.width = int(height), int(width)
        frames, problems = scan_frames(self.path)
        if problems:
            raise problems[0]
        if not frames:
            raise LayoutError(self.path / "color", "at least one <frame>.jpg", "no frames")
        poses = [read_pose(f.pose, f.token) for f in frames]
        valid = [pose_is_valid(p) for p in poses]
        dropped = len(frames) - sum(valid)
        if dropped:
            warnings.warn(
                f"{self.path}: dropped {dropped} of {len(frames)} frames whose pose is not finite "
                "(ScanNet marks lost tracking with -inf), together with their colour, depth, label and instance files",
                stacklevel=2,
            )
        self.files: list[FrameFiles] = [f for f, ok in zip(frames, valid) if ok]
        if not self.files:
            found = f"{len(frames)} invalid poses"
            raise LayoutError(self.path / "pose", "at least one frame with a finite pose", found)
        self.c2w = torch.from_numpy(np.stack([p for p, ok in zip(poses, valid) if ok])).float()
        self.color_size = image_size(self.files[0].color, self.files[0].token)
        k_color = read_intrinsic(self.path / INTRINSIC_COLOR)
        sx, sy = self.width / self.color_size[1], self.height / self.color_size[0]
        self.intrinsics = torch.from_numpy(scale_intrinsics(k_color, sx, sy)).float()
        self.k_depth = None
        if depth_alignment == "intrinsics":
            if (self.path / INTRINSIC_DEPTH).is_file():
                self.k_depth = read_intrinsic(self.path / INTRINSIC_DEPTH)
            else:
                warnings.warn(
                    f"{self.path / INTRINSIC_DEPTH}: missing; depth is resized to the colour camera instead of "
                    "registered with its own intrinsics (dataset.depth_alignment=resize does this silently)",
                    stacklevel=2,
                )
        self._k_color_out = scale_intrinsics(k_color, sx, sy)
        # The depth intrinsics describe one depth image size: the first frame's, which every depth image must have.
        self.depth_size = image_size(self.files[0].depth, self.files[0].token) if self.k_depth is not None else None
        self.dropped_invalid_poses = dropped
        self.decoder = ScanNetFrames(self)

    @property
    def num_frames(self) -> int:
        return len(self.files)

    @property
    def tokens(self) -> tuple[str, ...]:
        """Frame names in index order."""
        return tuple(f.token for f in self.files)

    def load_frame(self, index: int) -> Frame:
        """Decode frame ``index`` (position in the numeric order, invalid poses dropped) at ``height`` x ``width``."""
        if not 0 <= index < self.num_frames:
            raise LayoutError(self.path, f"a frame index in 0..{self.num_frames - 1}", str(index))
        files = self.files[index]
        decoded = DecodedFiles(files.color, files.depth, files.label, files.instance, name=files.token)
        return self.decoder.decode(decoded, self.intrinsics.clone(), self.c2w[index].clone())

    def scene(self, *, protocol: str = "heldout", near: float = 0.1, far: float = 6.0) -> Scene:
        """Wrap as a ``Scene`` named after the folder, frames split by ``frame_split(protocol)``."""
        near, far = check_depth_range(near, far)
        train, held = frame_split(self.tokens, protocol)
        return Scene(
            name=self.path.name,
            c2w=self.c2w.clone(),
            intrinsics=self.intrinsics.expand(self.num_frames, 3, 3).clone(),
            height=self.height,
            width=self.width,
            near=float(near),
            far=float(far),
            train_frames=train,
            eval_frames=held,
            load_frame=self.load_frame,
        )


class ScanNetFrames(FrameDecoder):
    """A ScanNet scene's frames: JPEG colour resized with PIL's antialiasing, depth registered to the colour camera (or
    resized, ``depth_alignment``), label ids mapped to the 20 classes, instance ids as stored.

    Args:
        scene: the scene whose files and cameras it decodes.
    """

    def __init__(self, scene: ScanNetScene) -> None:
        super().__init__((scene.height, scene.width), IGNORE_INDEX)
        self.scene = scene
        self._lookup: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._warned_unknown = False

    def rgb(self, files: DecodedFiles) -> np.ndarray:
        image = decode_image(files.rgb, files.name, "JPEG colour image")
        found = (image.height, image.width)
        if found != self.scene.color_size:
            raise LayoutError(
                files.rgb,
                f"{self.scene.color_size[1]}x{self.scene.color_size[0]} (WxH) like {self.scene.files[0].color.name}",
                f"{found[1]}x{found[0]}",
                files.name,
            )
        image = image.convert("RGB")
        if found != self.size:
            image = image.resize((self.size[1], self.size[0]), Image.Resampling.BILINEAR)
        return np.asarray(image, dtype=np.float32) / 255.0

    def _aligned(self, path: Path, files: DecodedFiles, kind: str) -> np.ndarray:
        values = read_integer_image(path, files.name, kind)
        if aspect_mismatch(values.shape, self.scene.color_size):
            raise LayoutError(
                path,
                f"the aspect ratio of the colour images ({self.scene.color_size[1]}x{self.scene.color_size[0]} WxH)",
                f"{values.shape[1]}x{values.shape[0]}",
                files.name,
            )
        return resize_nearest(values, *self.size)

    def depth(self, files: DecodedFiles) -> np.ndarray:
        """Depth in metres at the output size, 0 = unknown (registered or resized, see ``depth_alignment``)."""
        if self.scene.k_depth is None:
            return self._aligned(files.depth, files, "depth").astype(np.float32) / DEPTH_SCALE
        values = read_integer_image(files.depth, files.name, "depth")
        if values.shape[:2] != self.scene.depth_size:
            raise LayoutError(
                files.depth,
                f"{self.scene.depth_size[1]}x{self.scene.depth_size[0]} (WxH) like {self.scene.files[0].depth.name}, "
                f"the size {INTRINSIC_DEPTH} describes",
                f"{values.shape[1]}x{values.shape[0]}",
                files.name,
            )
        if self._lookup is None:
            self._lookup = depth_lookup(self.scene._k_color_out, self.scene.k_depth, *self.size, self.scene.depth_size)
        rows, cols, inside = self._lookup
        return np.where(inside, values[rows, cols], 0).astype(np.float32) / DEPTH_SCALE

    def _ids(self, path: Path, files: DecodedFiles, kind: str, what: str) -> np.ndarray:
        """Non-negative integer ids of a ``kind`` PNG, ``[height, width]`` int64, resized by nearest neighbour."""
        ids = self._aligned(path, files, kind)
        if ids.min(initial=0) < 0:
            raise LayoutError(path, f"non-negative {what}", f"{int(ids.min())}", files.name)
        return ids

    def instances(self, files: DecodedFiles) -> np.ndarray | None:
        """``instance-filt`` ids at the output size (0 = not annotated), or None when the scene has no instance maps."""
        if files.instance is None:
            return None
        return self._ids(files.instance, files, "instance", "instance ids")

    def labels(self, files: DecodedFiles) -> np.ndarray:
        raw = self._ids(files.semantic, files, "label", "ScanNet category ids")
        labels, unknown, count = self.scene.label_map.apply(raw)
        if count and not self._warned_unknown:
            self._warned_unknown = True
            shown = ", ".join(str(int(v)) for v in unknown[:8]) + (", ..." if len(unknown) > 8 else "")
            warnings.warn(
                f"{self.scene.path.name}: {count} label pixels of frame {files.name} have ids {shown} that "
                f"{self.scene.label_map.path} does not list; mapped to ignore ({IGNORE_INDEX}) "
                "(reported once per scene)",
                stacklevel=3,
            )
        return labels

