"""viser's camera and the framework's camera, both OpenCV: +X right, +Y down, +Z forward (viser documents its cameras
and frustums so), so the pose carries over as it is; only the quaternion and the pinhole matrix are converted."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


@dataclass(frozen=True)
class PinholeView:
    """A target camera for the renderer.

    Attributes:
        c2w: ``[4, 4]`` float32 camera-to-world (OpenCV). intrinsics: ``[3, 3]`` float32 pinhole matrix at
        ``height`` x ``width`` pixels.
    """

    c2w: Tensor
    intrinsics: Tensor
    height: int
    width: int


def rotation_from_wxyz(wxyz: np.ndarray | tuple[float, ...]) -> np.ndarray:
    """``[3, 3]`` rotation of a (w, x, y, z) quaternion (normalised first; a zero quaternion is refused)."""
    q = np.asarray(wxyz, dtype=np.float64).reshape(4)
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or norm == 0.0:
        raise ValueError(f"camera orientation {q.tolist()} is not a rotation quaternion")
    w, x, y, z = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def wxyz_from_rotation(rotation: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a ``[3, 3]`` rotation matrix, w >= 0 (Shepperd's method: stable for every angle)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    quaternion = np.array(q)
    quaternion /= np.linalg.norm(quaternion)
    return -quaternion if quaternion[0] < 0 else quaternion


def viser_pose(c2w: Tensor | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(wxyz, position)`` that place a viser camera or frustum at the OpenCV camera-to-world ``c2w`` ``[4, 4]``."""
    matrix = c2w.detach().cpu().double().numpy() if isinstance(c2w, Tensor) else np.asarray(c2w, dtype=np.float64)
    return wxyz_from_rotation(matrix[:3, :3]), matrix[:3, 3].copy()


def vertical_fov(intrinsics: Tensor | np.ndarray, height: int) -> float:
    """Vertical field of view in radians of a pinhole matrix at ``height`` pixels."""
    fy = float(intrinsics[1][1])
    return 2.0 * math.atan(height / (2.0 * fy))


def view_from_viser(
    wxyz: np.ndarray | tuple[float, ...],
    position: np.ndarray | tuple[float, ...],
    fov: float,
    aspect: float,
    height: int,
    multiple: int,
) -> PinholeView:
    """The framework's camera for a viser camera.

    Args:
        wxyz, position: the viser camera's orientation and centre in world coordinates.
        fov: vertical field of view, radians, in (0, pi); aspect: canvas width / height (> 0).
        height: rendered image height in pixels (the scene's); the width follows the aspect, rounded to a multiple of
            ``multiple`` (the render strides must divide it), at least ``multiple``.

    Returns:
        The pose and a centred pinhole with square pixels, ``fy = height / (2 tan(fov / 2))``, principal point
        ``((W - 1) / 2, (H - 1) / 2)``.
    """
    if not (0.0 < fov < math.pi) or not (math.isfinite(aspect) and aspect > 0):
        raise ValueError(f"camera fov={fov} rad, aspect={aspect}: expected 0 < fov < pi and a positive aspect")
    centre = np.asarray(position, dtype=np.float64).reshape(3)
    if not np.isfinite(centre).all():
        raise ValueError(f"camera position {centre.tolist()} is not finite")
    width = max(multiple, int(round(height * aspect / multiple)) * multiple)
    focal = height / (2.0 * math.tan(fov / 2.0))
    c2w = np.eye(4)
    c2w[:3, :3] = rotation_from_wxyz(wxyz)
    c2w[:3, 3] = centre
    # The framework puts pixel (u, v)'s centre at integer coordinates (``geometry.pixel_grid``): the image centre is
    # ((W - 1) / 2, (H - 1) / 2), as the datasets' intrinsics have it.
    intrinsics = np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return PinholeView(
        c2w=torch.from_numpy(c2w).float(), intrinsics=torch.from_numpy(intrinsics).float(), height=height, width=width
    )
