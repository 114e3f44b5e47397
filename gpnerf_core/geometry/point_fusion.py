"""Rendered depth maps to one point cloud: back-projection, the multi-view depth-consistency check that MVS fusion uses
(a point is kept where other rendered views saw a surface at the same depth), and voxel merging.

Cameras are OpenCV (x right, y down, z forward), ``c2w`` camera-to-world, depth the camera z in metres (the ray
parameter of ``geometry.rays``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from gpnerf_core.geometry.projection import project_points
from gpnerf_core.geometry.rays import pixel_grid


@dataclass(frozen=True)
class DepthView:
    """One rendered view: its depth on a pixel grid and the camera that saw it.

    Attributes:
        depth: ``[h, w]`` metres (camera z) at the grid cells.
        pixels: ``[h * w, 2]`` the cells' ``(u, v)`` in full-image pixels, row-major (``geometry.rays.pixel_grid``).
        intrinsics: ``[3, 3]`` at the full image size; c2w: ``[4, 4]``.
        height, width: the full image size, pixels.
    """

    depth: Tensor
    pixels: Tensor
    intrinsics: Tensor
    c2w: Tensor
    height: int
    width: int


def backproject(view: DepthView) -> Tensor:
    """World points ``[h * w, 3]`` of the view's cells: ``c2w @ (depth * K^-1 [u, v, 1])``."""
    ones = torch.ones_like(view.pixels[:, :1])
    rays = torch.cat([view.pixels, ones], dim=-1) @ torch.linalg.inv(view.intrinsics).T  # camera z = 1
    camera_points = rays * view.depth.reshape(-1, 1)
    return camera_points @ view.c2w[:3, :3].T + view.c2w[:3, 3]


def rendered_view(prediction: Any, camera: Any) -> DepthView:
    """A ``Prediction``'s depth on its stride grid as the ``DepthView`` of ``camera`` (a ``TargetCamera``), on the
    CPU."""
    return DepthView(depth=prediction.depth.detach().float().cpu(),
                     pixels=pixel_grid(camera.height, camera.width, prediction.stride),
                     intrinsics=camera.intrinsics.float().cpu(), c2w=camera.c2w.float().cpu(),
                     height=camera.height, width=camera.width)


def cell_scores(prediction: Any) -> Tensor:
    """``[K, h, w]`` each rendered cell's mean score (``prediction.logits`` ``[1, K, H, W]`` pooled over the cell's
    ``stride`` x ``stride`` pixels, NaN as 0), on the CPU, the rendered grid's shape."""
    stride, depth = prediction.stride, prediction.depth
    scores = torch.nan_to_num(prediction.logits.detach().float().cpu())
    cells = torch.nn.functional.avg_pool2d(scores, stride)[0] if stride > 1 else scores[0]
    return cells[:, : depth.shape[0], : depth.shape[1]]


def inside_bounds(depth: Tensor, scene: Any) -> Tensor:
    """``[N]`` bool: a finite depth strictly inside the scene's sampling bounds (a ray that met nothing renders a
    depth at the far bound)."""
    margin = 1e-3 * (scene.far - scene.near)
    return torch.isfinite(depth) & (depth > scene.near + margin) & (depth < scene.far - margin)


def nearest_cells(points: Tensor, view: DepthView) -> tuple[Tensor, Tensor, Tensor]:
    """``(inside [N] bool, the point's depth in view [N], the row-major index of its nearest grid cell [N])``: the
    cell whose centre is nearest the point's projection (clamped to the grid where the point falls outside it)."""
    pixels, depth = project_points(points, view.intrinsics[None], view.c2w[None])
    pixels, depth = pixels[0], depth[0]
    grid_h, grid_w = view.depth.shape
    stride = view.height / grid_h
    col = torch.floor((pixels[:, 0] + 0.5) / stride).long()  # pixel centres are at integer coordinates
    row = torch.floor((pixels[:, 1] + 0.5) / stride).long()
    inside = (depth > 0) & (col >= 0) & (col < grid_w) & (row >= 0) & (row < grid_h)
    return inside, depth, row.clamp(0, grid_h - 1) * grid_w + col.clamp(0, grid_w - 1)


def _looked_up(points: Tensor, other: DepthView) -> tuple[Tensor, Tensor, Tensor]:
    """``(inside [N] bool, the point's depth in other [N], other's rendered depth at its nearest cell [N])``."""
    inside, depth, cell = nearest_cells(points, other)
    return inside, depth, other.depth.reshape(-1)[cell]


def free_space_conflict(points: Tensor, other: DepthView, tolerance: float) -> Tensor:
    """``[N]`` bool: the point lies inside ``other``'s image in front of the surface ``other`` rendered there by more
    than ``tolerance`` (relative): ``other`` sees through it, so it is a floater in ``other``'s free space."""
    inside, depth, seen = _looked_up(points, other)
    return inside & (seen > 0) & (depth < (1.0 - tolerance) * seen)


def conflicting_views(views: list[DepthView], tolerance: float) -> list[Tensor]:
    """Per view, ``[h * w]`` int: how many of the other views see through each of its points
    (``free_space_conflict``): the visibility check of depth-map fusion, which removes floaters a point's agreement
    with other views (``agreeing_views``) keeps when two views err alike."""
    return counted_over_views(views, lambda points, other: free_space_conflict(points, other, tolerance))


def counted_over_views(views: list[DepthView], test: Any) -> list[Tensor]:
    """Per view, ``[h * w]`` int: for how many of the other views ``test(its points, other view)`` holds."""
    points = [backproject(view) for view in views]
    counts = []
    for index, own in enumerate(points):
        count = torch.zeros(own.shape[0], dtype=torch.long, device=own.device)
        for other_index, other in enumerate(views):
            if other_index != index:
                count += test(own, other).long()
        counts.append(count)
    return counts


def depth_agreement(points: Tensor, other: DepthView, tolerance: float) -> Tensor:
    """``[N]`` bool: the point is in front of ``other``'s camera, inside its image, and ``other``'s rendered depth at
    the nearest grid cell is within ``tolerance`` (relative) of the point's depth there.

    The grid is ``other.pixels``' regular stride grid; a point is looked up at the cell whose centre is nearest.
    """
    inside, depth, seen = _looked_up(points, other)
    return inside & ((depth - seen).abs() <= tolerance * seen.abs())


def agreeing_views(views: list[DepthView], tolerance: float) -> list[Tensor]:
    """Per view, ``[h * w]`` int: how many of the other views agree with each of its points (``depth_agreement``)."""
    return counted_over_views(views, lambda points, other: depth_agreement(points, other, tolerance))


@dataclass(frozen=True)
class PointCloud:
    """Points with their colour and label.

    Attributes:
        xyz: ``[N, 3]`` float32 metres; rgb: ``[N, 3]`` float32 in [0, 1]; label: ``[N]`` int64 (class or instance
            slot; -1 = none).
    """

    xyz: Tensor
    rgb: Tensor
    label: Tensor

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def concatenate(clouds: list[PointCloud]) -> PointCloud:
    """One cloud of all points, in order."""
    return PointCloud(torch.cat([c.xyz for c in clouds]), torch.cat([c.rgb for c in clouds]),
                      torch.cat([c.label for c in clouds]))


def voxel_merge(cloud: PointCloud, voxel: float) -> PointCloud:
    """One point per occupied cube of side ``voxel`` metres: the mean position and colour of its points and their
    most frequent label (the lowest on a tie). Points come out ordered by voxel (deterministic)."""
    if voxel <= 0 or len(cloud) == 0:
        return cloud
    cells = torch.floor(cloud.xyz.double() / voxel).long()
    _, voxel_of = torch.unique(cells, dim=0, return_inverse=True)
    count = torch.bincount(voxel_of).unsqueeze(1).double()
    num = count.shape[0]
    xyz = torch.zeros(num, 3, dtype=torch.float64).index_add_(0, voxel_of, cloud.xyz.double()) / count
    rgb = torch.zeros(num, 3, dtype=torch.float64).index_add_(0, voxel_of, cloud.rgb.double()) / count
    offset = int(cloud.label.min())
    span = int(cloud.label.max()) - offset + 1
    votes = torch.zeros(num * span, dtype=torch.long)
    votes.index_add_(0, voxel_of * span + (cloud.label - offset), torch.ones_like(voxel_of))
    label = votes.view(num, span).argmax(dim=1) + offset
    return PointCloud(xyz.float(), rgb.float(), label)
