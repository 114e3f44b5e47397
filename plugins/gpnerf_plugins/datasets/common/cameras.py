"""Pinhole intrinsics under image resizes, shared by the dataset readers."""

from __future__ import annotations

import numpy as np


def scale_intrinsics(k: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics ``[3, 3]`` after resizing the image by ``sx`` horizontally and ``sy`` vertically.

    Pixel centres sit at integers (``gpnerf_core.types``), so a resize maps ``u + 0.5`` to ``sx (u + 0.5)``:
    ``fx' = sx fx``, ``cx' = sx (cx + 0.5) - 0.5`` (likewise in y). This is the mapping of area-aligned
    resizes (PIL, skimage, the nearest-neighbour pick of ``image_io.resize_nearest``).
    """
    a = np.array([[sx, 0.0, (sx - 1.0) / 2.0], [0.0, sy, (sy - 1.0) / 2.0], [0.0, 0.0, 1.0]])
    return a @ k
