"""A capture's sparse point cloud (``ply_file_path``, ``sparse_points.ply``) read and validated.

pycolmap's reader parses the PLY; what it lets through is refused here, each a ``DataError`` naming the file: a file
it cannot parse (random bytes, no ``vertex`` element with ``x``/``y``/``z`` columns), fewer points than the header
declares (a truncated binary file reads short without a word), and NaN or Inf coordinates.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from gpnerf_core import DataError

EXPECTED = "expected the PLY of ply_file_path (a vertex element with float x, y, z; `data import-colmap` writes one)"

HEADER_LIMIT = 1 << 16
"""Bytes of the file searched for the header's ``end_header`` line."""


def declared_vertices(path: Path) -> int | None:
    """The vertex count the PLY header of ``path`` declares, or None when no header is found in its first bytes."""
    with open(path, "rb") as stream:
        head = stream.read(HEADER_LIMIT)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return None
    found = re.search(rb"^element vertex (\d+)\s*$", head[:end], flags=re.MULTILINE)
    return int(found.group(1)) if found else None


def read_point_cloud(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(xyz [P, 3] float64, rgb [P, 3] uint8)`` of the PLY at ``path``, in the file's world; a malformed file is a
    one-line ``DataError`` naming it (the module docstring)."""
    import pycolmap

    declared = declared_vertices(path) if path.is_file() else None
    cloud = pycolmap.Reconstruction()
    try:
        cloud.import_PLY(str(path))
    except Exception as exc:  # pycolmap raises its own exception types for a missing or malformed file
        reason = " ".join(str(exc).split())
        raise DataError(f"{path}: unreadable point cloud ({type(exc).__name__}: {reason}); {EXPECTED}") from None
    points = list(cloud.points3D.values())
    if declared is None and points:
        raise DataError(f"{path}: no PLY header declaring a vertex element; {EXPECTED}")
    if declared is not None and len(points) != declared:
        raise DataError(f"{path}: holds {len(points)} of the {declared} points its header declares (a truncated or "
                        f"damaged file); {EXPECTED}")
    if not points:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    xyz = np.stack([p.xyz for p in points])
    check_finite_points(path, xyz)
    return xyz, np.stack([p.color for p in points]).astype(np.uint8)


def check_finite_points(path: Path, xyz: np.ndarray, where: str = "") -> None:
    """A ``DataError`` naming ``path`` when a row of ``xyz`` ``[P, 3]`` holds NaN or Inf (``where``: after what)."""
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise DataError(f"{path}: {int(bad.sum())} of {len(xyz)} sparse points have NaN or Inf coordinates{where}; "
                        f"expected finite x, y, z: re-export the points or "
                        "remove ply_file_path")
