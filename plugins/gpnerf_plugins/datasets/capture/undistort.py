"""Undoing OpenCV lens distortion (``k1 k2 p1 p2 k3``) of a capture's images, depth, masks and labels.

Each pixel centre of the undistorted image (same intrinsics, same size) is sent through kornia's ``distort_points``
to where the lens put it, and the stored image is sampled there: bilinearly for colour, at the nearest pixel for
depth, masks and class ids (values are never blended). Pixels whose source falls outside the stored image have no
data: colour 0, depth 0 (unknown), mask 0 (ignored), labels the ignore index.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.calibration import distort_points


class Undistorter:
    """The sampling grid of one camera, built once and applied to every image of that camera.

    Args:
        intrinsics: ``[3, 3]`` pinhole matrix, pixel centres at integers.
        distortion: ``(k1, k2, p1, p2, k3)``.
        height, width: the stored image size, pixels.
    """

    def __init__(self, intrinsics: np.ndarray, distortion: tuple[float, ...], height: int, width: int) -> None:
        k = torch.as_tensor(intrinsics, dtype=torch.float64)
        v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                              indexing="ij")
        pixels = torch.stack([u, v], dim=-1).reshape(-1, 2)
        source = distort_points(pixels, k, torch.as_tensor(distortion, dtype=torch.float64)).reshape(height, width, 2)
        scale = torch.tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)], dtype=torch.float64)
        self.grid = (source * scale - 1.0).float()[None]  # [1, H, W, 2], align_corners=True coordinates
        self.height, self.width = height, width

    def _sample(self, image: np.ndarray, mode: str) -> np.ndarray:
        planar = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))
        planar = planar[None, None] if planar.ndim == 2 else planar.permute(2, 0, 1)[None]
        out = F.grid_sample(planar, self.grid, mode=mode, padding_mode="zeros", align_corners=True)[0]
        return out[0].numpy() if image.ndim == 2 else out.permute(1, 2, 0).numpy()

    def rgb(self, rgb: np.ndarray) -> np.ndarray:
        """``[H, W, 3]`` float32 colours in [0, 1]."""
        return np.clip(self._sample(rgb, "bilinear"), 0.0, 1.0)

    def values(self, values: np.ndarray) -> np.ndarray:
        """``[H, W]`` depth or mask values (float), nearest pixel; 0 where the lens saw nothing."""
        return self._sample(values, "nearest")

    def labels(self, labels: np.ndarray, ignore_index: int) -> np.ndarray:
        """``[H, W]`` int64 class ids, nearest pixel; ``ignore_index`` where the lens saw nothing."""
        shifted = self._sample(labels.astype(np.float32) + 1.0, "nearest")
        return np.where(shifted > 0, np.rint(shifted) - 1, ignore_index).astype(np.int64)
