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
        else:
            check_points_in_view(scene, points)
    if points is None:
        points, origin = depth_points(scene, depth_stride), "depth"
    if points is None:
        if depth_stride > 1 and depth_points(scene, 1) is not None:
            raise DataError(f"scene {scene.name!r}: model.init_depth_stride={depth_stride} meets no valid depth in "
                            f"its training frames ({scene.height}x{scene.width}: every {depth_stride}-th pixel from "
                            f"(0, 0) has none); expected a finer stride: model.init_depth_stride="
                            f"{_coarsest_working_stride(scene, depth_stride)} meets some")
        raise DataError(f"scene {scene.name!r} has no sparse points (a capture's ply_file_path, which `data "
                        "prepare-capture` and `data import-colmap` write) and no depth in its training frames; "
                        "a per-scene Gaussian model starts its Gaussians from one of them")
    if points.count > limit:
        chosen = torch.randperm(points.count)[:limit].sort().values
        points = ScenePoints(xyz=points.xyz[chosen], rgb=points.rgb[chosen])
    return points, origin


def _coarsest_working_stride(scene: Scene, stride: int) -> int:
    """The coarsest stride below ``stride`` whose pixels meet some valid depth (1 does: the caller checked)."""
    for candidate in range(stride - 1, 1, -1):
        if depth_points(scene, candidate) is not None:
            return candidate
    return 1


def check_points_in_view(scene: Scene, points: ScenePoints, near: float = 0.01) -> None:
    """A ``DataError`` naming the scene's sparse points when not one of them lies in front of a training camera (camera
    z > ``near`` metres) inside its image: they are in another frame than the poses, and every Gaussian started
    from them would be invisible to every training view."""
    xyz = points.xyz.double()
    for index in scene.train_frames:
        c2w, k = scene.c2w[index].double(), scene.intrinsics[index].double()
        camera = (xyz - c2w[:3, 3]) @ c2w[:3, :3]
        z = camera[:, 2]
        front = z > near
        u = k[0, 0] * camera[front, 0] / z[front] + k[0, 2]
        v = k[1, 1] * camera[front, 1] / z[front] + k[1, 2]
        if bool(((u > -0.5) & (u < scene.width - 0.5) & (v > -0.5) & (v < scene.height - 0.5)).any()):
            return
    raise DataError(f"scene {scene.name!r}: none of its {points.count} sparse points (a capture's ply_file_path, "
                    f"sparse_points.ply) lies in front of a training camera inside its image: the points are in "
                    f"another frame than the poses; expected points in the poses' world (a capture's "
                    f"applied_transform, or the COLMAP model the poses came from)")


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
