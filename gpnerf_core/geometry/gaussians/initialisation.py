"""Where a scene's Gaussians start (3DGS's ``create_from_pcd``): points with colours, and the scene's extent.

The points are the scene's sparse points where it has them (a capture's structure from motion, as the official code
starts from COLMAP's), else its training frames' depth back-projected (datasets with depth: the embedded scenes,
Replica, ScanNet); a random subset of at most a limit. Each point becomes a Gaussian (``parameters.rows_from_points``)
with its colour as the degree-0 harmonic, an isotropic scale of the root mean squared distance to its three nearest
neighbours (``neighbour_scales``), no rotation and the family's starting opacity (3DGS: 0.1). The extent is 3DGS's
``getNerfppNorm`` radius: 1.1 x the largest distance of a training camera from their mean centre. Another model's
Gaussians start a scene through ``parameters.rows_from_gaussians``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from gpnerf_core.errors import DataError
from gpnerf_core.types import Scene, ScenePoints

NEIGHBOURS = 3
"""Nearest neighbours whose mean squared distance sets a starting scale (3DGS's ``distCUDA2``)."""
MIN_SQUARED_DISTANCE = 1e-7
"""Clamp on that mean (3DGS's), so duplicate points get a tiny, not a zero, scale."""
ROWS_PER_CHUNK = 1024
"""Points whose neighbours are searched at once (bounds the distance matrix's memory: 1024 x P floats)."""


def scene_extent(scene: Scene) -> float:
    """Radius of the training cameras: 1.1 x the largest distance of a camera centre from their mean, metres."""
    centres = scene.c2w[list(scene.train_frames), :3, 3].double()
    radius = (centres - centres.mean(dim=0)).norm(dim=-1).max()
    return float(radius) * 1.1 if float(radius) > 0 else 1.0


def starting_points(scene: Scene, limit: int, depth_stride: int) -> tuple[ScenePoints, str]:
    """The points the scene's Gaussians start from and where they came from (``sparse points`` or ``depth``); a
    random subset of at most ``limit`` (the global random stream). A ``DataError`` naming the scene when it has
    neither sparse points nor depth in its training frames."""
    points, origin = None, ""
    if scene.sparse_points is not None:
        points, origin = scene.sparse_points(), "sparse points"
        if points.count == 0:
            points = None
    if points is None:
        points, origin = depth_points(scene, depth_stride), "depth"
    if points is None:
        raise DataError(f"scene {scene.name!r} has no sparse points (a capture's ply_file_path, which `data "
                        "prepare-capture` and `data import-colmap` write) and no depth in its training frames; "
                        "a per-scene Gaussian model starts its Gaussians from one of them")
    if points.count > limit:
        chosen = torch.randperm(points.count)[:limit].sort().values
        points = ScenePoints(xyz=points.xyz[chosen], rgb=points.rgb[chosen])
    return points, origin


def depth_points(scene: Scene, stride: int) -> ScenePoints | None:
    """Every ``stride``-th pixel with depth of every training frame, back-projected into the world with its colour;
    None when no training frame has depth."""
    xyz, rgb = [], []
    for index in scene.train_frames:
        frame = scene.load_frame(index)
        depth = frame.depth[::stride, ::stride].float()
        keep = depth > 0
        if frame.valid is not None:
            keep &= frame.valid[::stride, ::stride]
        if not bool(keep.any()):
            continue
        rows, cols = torch.nonzero(keep, as_tuple=True)
        u, v, z = (cols * stride).float(), (rows * stride).float(), depth[keep]
        k = frame.intrinsics.float()
        camera = torch.stack([(u - k[0, 2]) / k[0, 0] * z, (v - k[1, 2]) / k[1, 1] * z, z], dim=-1)
        c2w = frame.c2w.float()
        xyz.append(camera @ c2w[:3, :3].T + c2w[:3, 3])
        rgb.append(frame.rgb[::stride, ::stride][keep].float())
    if not xyz:
        return None
    return ScenePoints(xyz=torch.cat(xyz), rgb=torch.cat(rgb).clamp(0, 1))


def neighbour_scales(xyz: Tensor) -> Tensor:
    """``[P]`` the root of the mean squared distance of each point to its ``NEIGHBOURS`` nearest others."""
    count = xyz.shape[0]
    if count <= 1:
        return torch.full((count,), MIN_SQUARED_DISTANCE ** 0.5)
    k = min(NEIGHBOURS, count - 1)
    means = []
    points = xyz.double()
    for start in range(0, count, ROWS_PER_CHUNK):
        block = points[start:start + ROWS_PER_CHUNK]
        squared = torch.cdist(block, points).square()
        squared[torch.arange(block.shape[0]), torch.arange(start, start + block.shape[0])] = float("inf")
        means.append(squared.topk(k, dim=1, largest=False).values.mean(dim=1))
    return torch.cat(means).clamp_min(MIN_SQUARED_DISTANCE).sqrt().float()
