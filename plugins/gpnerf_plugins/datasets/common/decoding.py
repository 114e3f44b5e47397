"""One frame decoder for every built-in layout: a frame's files become a ``Frame`` at the dataset's size.

``FrameDecoder.decode`` reads, in this order, the colour, the depth, the class labels, the instance ids and the mask of
a frame, applies the mask (pixels it drops get the ignore label and unknown depth) and makes the tensors. Each read is
a hook; the defaults read the Replica layout's PNGs (8-bit RGB, 16-bit millimetre depth, integer ids) and resize them
(colour with antialiasing, everything else by nearest neighbour). A layout overrides the hooks where it differs:
ScanNet (JPEG colour, depth registered to the colour camera, ScanNet ids mapped to its 20 classes), a capture
(undistortion, depth in any unit or ``.npy``, masks).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from gpnerf_core import DataError, Frame
from gpnerf_plugins.datasets.common.image_io import read_integer_png, read_rgb_png, resize_nearest, resize_rgb

DEPTH_UNITS_PER_METRE = 1000.0
"""Depth PNGs hold millimetres (Replica, ScanNet, the embedded scenes)."""


@dataclass(frozen=True)
class FrameFiles:
    """The files of one frame; None for a kind this frame (or its layout) has none of.

    Attributes:
        name: the frame's name in messages (its number or file stem).
    """

    rgb: Path
    depth: Path | None = None
    semantic: Path | None = None
    instance: Path | None = None
    mask: Path | None = None
    name: str = ""


class FrameDecoder:
    """Decodes one frame's files at ``size`` (height, width) into a ``Frame``.

    Args:
        size: the dataset's frame size in pixels.
        ignore_index: the label of unlabelled pixels (and of pixels a mask drops).
    """

    def __init__(self, size: tuple[int, int], ignore_index: int) -> None:
        self.size = (int(size[0]), int(size[1]))
        self.ignore_index = int(ignore_index)

    # ---- hooks: one per kind of file -----------------------------------------------------------------------------

    def rgb(self, files: FrameFiles) -> np.ndarray:
        """``[H, W, 3]`` float32 colours in [0, 1] at the size."""
        return resize_rgb(read_rgb_png(files.rgb), *self.size)

    def depth(self, files: FrameFiles) -> np.ndarray:
        """``[H, W]`` float32 metres at the size, 0 where unknown (all 0 without a depth file)."""
        if files.depth is None:
            return np.zeros(self.size, dtype=np.float32)
        stored = resize_nearest(read_integer_png(files.depth, "depth in millimetres", depth=True), *self.size)
        return stored.astype(np.float32) / DEPTH_UNITS_PER_METRE

    def labels(self, files: FrameFiles) -> np.ndarray:
        """``[H, W]`` int64 class ids or the ignore index at the size (all ignored without a label file)."""
        if files.semantic is None:
            return np.full(self.size, self.ignore_index, dtype=np.int64)
        return resize_nearest(self.class_ids(read_integer_png(files.semantic, "class ids"), files), *self.size)

    def class_ids(self, stored: np.ndarray, files: FrameFiles) -> np.ndarray:
        """The dataset's class ids of a label file's values (default: the values themselves)."""
        return stored

    def instances(self, files: FrameFiles) -> np.ndarray | None:
        """``[H, W]`` int64 instance ids at the size, or None without an instance file."""
        if files.instance is None:
            return None
        return resize_nearest(read_integer_png(files.instance, "instance ids"), *self.size)

    def keep(self, files: FrameFiles) -> np.ndarray | None:
        """``[H, W]`` bool, False where the frame's mask drops the pixel; None without a mask."""
        return None

    # ---- the frame ------------------------------------------------------------------------------------------------

    def decode(self, files: FrameFiles, intrinsics: Tensor, c2w: Tensor) -> Frame:
        """The frame of ``files`` with its camera (``[3, 3]`` intrinsics at the size, ``[4, 4]`` camera-to-world)."""
        rgb = self.rgb(files)
        depth = self.depth(files)
        labels = self.labels(files)
        instances = self.instances(files)
        keep = self.keep(files)
        valid = None
        if keep is not None:
            if not keep.any():
                raise DataError(f"{files.mask}: the mask keeps no pixel of frame {files.name!r}; expected 0 only where "
                                "pixels are to be ignored")
            labels = np.where(keep, labels, self.ignore_index)
            depth = np.where(keep, depth, 0.0).astype(np.float32)
            valid = _tensor(keep)
        return Frame(
            rgb=_tensor(rgb),
            depth=_tensor(depth),
            semantic=_tensor(labels),
            intrinsics=intrinsics,
            c2w=c2w,
            instance=None if instances is None else _tensor(instances),
            valid=valid,
        )


def _tensor(array: np.ndarray) -> Tensor:
    return torch.from_numpy(np.ascontiguousarray(array))
