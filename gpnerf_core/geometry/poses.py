"""Checks on camera poses: a camera-to-world matrix must be a rigid transform."""

from __future__ import annotations

import numpy as np

RIGID_TOLERANCE = 1e-3
"""Largest accepted deviation of ``R^T R`` from the identity and of ``det R`` from 1 (poses stored as text in
float32 are far closer; a scaled, sheared or mirrored camera is far off)."""

EXPECTED_RIGID = "a rigid transform (rotation orthonormal with determinant +1, last row 0 0 0 1)"


def rigid_transform_problem(c2w: np.ndarray, tolerance: float = RIGID_TOLERANCE) -> str | None:
    """What is wrong with a ``[4, 4]`` camera-to-world matrix, in a few words, or None if it is rigid.

    The caller names the file and line (or scene and frame) and uses ``EXPECTED_RIGID`` for what was expected.
    """
    pose = np.asarray(c2w, dtype=np.float64)
    if pose.shape != (4, 4):
        return f"shape {list(pose.shape)}"
    if not np.isfinite(pose).all():
        return "NaN or Inf in the pose"
    if np.abs(pose[3] - (0.0, 0.0, 0.0, 1.0)).max() > tolerance:
        return f"last row {' '.join(f'{v:g}' for v in pose[3])}"
    rotation = pose[:3, :3]
    deviation = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if deviation > tolerance:
        return f"rotation not orthonormal (max |R^T R - I| = {deviation:.3g})"
    determinant = float(np.linalg.det(rotation))
    if abs(determinant - 1.0) > tolerance:
        return f"rotation determinant {determinant:.3g}" + (" (a mirror)" if determinant < 0 else "")
    return None
