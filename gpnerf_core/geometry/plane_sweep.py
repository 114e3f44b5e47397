"""Plane-sweep cost volumes in a reference view's frustum (MVSNet, MVSNeRF): source maps warped onto fronto-parallel
planes of the reference camera, and the variance of their features over the views that see each voxel.

A ``ReferenceFrustum`` cuts the reference camera's view between ``near`` and ``far`` into a voxel grid: D planes at
camera depths ``depths()`` (uniform in depth, or in 1/depth), each tiled by the h x w cells of a map of the reference
image (cell (i, j) is centred on the full-resolution pixel ``((j + 0.5) W / w - 0.5, (i + 0.5) H / h - 0.5)``, so a
1/4 feature map's cells are the voxels' columns), optionally widened by whole cells on each side (``pad``: MVSNeRF's
frustum padding, for target rays that leave the reference image). A volume over it is ``[C, D, h', w']`` with
``h' = h + 2 pad_rows`` and ``w' = w + 2 pad_cols``.

``plane_sweep`` finds where every voxel centre lands in V views (the back-projection of the reference pixel at the
plane's depth, projected again: the plane homography); ``PlaneSweep.warp`` samples any ``[V, C, h_m, w_m]`` maps there
(bilinear, zero outside); ``variance_over_views`` gives MVSNet's cost. ``ReferenceFrustum.sample`` reads a volume at
world points (trilinear, zero outside), and ``points_in_views`` gives the ``grid_sample`` coordinates of world points
in V views.

Conventions are ``gpnerf_core.types``'s: OpenCV cameras, camera-to-world poses, metres, depth = camera z, pixel centres
at integer coordinates, ``grid_sample`` with ``align_corners=False`` on images (their edges at +-1).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from gpnerf_core.geometry.projection import normalized_grid, project_points, world_to_camera

MIN_DEPTH = 1e-6
"""Points at or behind a camera's plane (camera z at most this, metres) are outside its view."""


def points_in_views(
    points: Tensor, intrinsics: Tensor, c2w: Tensor, image_size: tuple[int, int]
) -> tuple[Tensor, Tensor]:
    """Where world points land in V views of ``image_size`` (H, W) pixels.

    Args:
        points: ``[N, 3]`` world positions, metres.
        intrinsics: ``[V, 3, 3]`` at ``image_size``; c2w: ``[V, 4, 4]``.

    Returns:
        ``grid`` ``[V, N, 2]``: ``grid_sample`` coordinates (``align_corners=False``: +-1 are the image edges, so one
        grid samples a map of any resolution that tiles the image); ``inside`` ``[V, N]`` bool: the point is in front
        of the camera and its projection within the image (edges included).
    """
    return projections_in_views(*project_points(points, intrinsics, c2w), image_size)


def projections_in_views(pixels: Tensor, depth: Tensor, image_size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """``points_in_views`` of points already projected: ``pixels`` ``[V, N, 2]`` and camera ``depth`` ``[V, N]`` as
    ``project_points`` gives them, for a caller that projects its own way or also needs the depth."""
    height, width = image_size
    inside = (
        (depth > MIN_DEPTH)
        & (pixels[..., 0] >= -0.5) & (pixels[..., 0] <= width - 0.5)
        & (pixels[..., 1] >= -0.5) & (pixels[..., 1] <= height - 0.5)
    )
    return normalized_grid(pixels, height, width), inside


@dataclass(frozen=True)
class ReferenceFrustum:
    """The voxel grid of a reference camera's frustum (the module docstring states its layout).

    Attributes:
        intrinsics: ``[3, 3]`` at ``image_size``; c2w: ``[4, 4]`` camera-to-world (OpenCV, metres).
        image_size: (H, W) of the reference image, pixels.
        cells: (h, w) cells tiling the image (a feature map's size: (H / 4, W / 4) for a 1/4 map).
        near, far: depths of the first and last plane, metres (0 < near < far).
        num_planes: D >= 2.
        inverse_depth: planes uniform in 1/depth (MVSNeRF's ``lindisp``) instead of in depth.
        pad: (rows, columns) of cells added on each side (0, 0: the image's cells only).
    """

    intrinsics: Tensor
    c2w: Tensor
    image_size: tuple[int, int]
    cells: tuple[int, int]
    near: float
    far: float
    num_planes: int
    inverse_depth: bool = False
    pad: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        if not 0 < self.near < self.far or self.num_planes < 2 or min(self.cells) < 1 or min(self.pad) < 0:
            raise ValueError(f"frustum near {self.near}, far {self.far}, {self.num_planes} planes, cells {self.cells}, "
                             f"pad {self.pad}: expected 0 < near < far, at least 2 planes, cells >= 1 and pad >= 0")

    @property
    def volume_size(self) -> tuple[int, int, int]:
        """(D, h', w'): a volume over the frustum is ``[C, D, h', w']`` (the cells and their padding)."""
        return self.num_planes, self.cells[0] + 2 * self.pad[0], self.cells[1] + 2 * self.pad[1]

    def depths(self) -> Tensor:
        """``[D]`` ascending plane depths from ``near`` to ``far`` (both included), metres."""
        steps = torch.linspace(0.0, 1.0, self.num_planes, device=self.c2w.device, dtype=self.c2w.dtype)
        if self.inverse_depth:
            return 1.0 / (1.0 / self.near * (1.0 - steps) + 1.0 / self.far * steps)
        return self.near * (1.0 - steps) + self.far * steps

    def voxel_centres(self) -> Tensor:
        """``[D, h', w', 3]`` world positions of the voxel centres, metres."""
        (height, width), (rows, cols), (pad_rows, pad_cols) = self.image_size, self.cells, self.pad
        kwargs = {"device": self.c2w.device, "dtype": self.c2w.dtype}
        v = (torch.arange(-pad_rows, rows + pad_rows, **kwargs) + 0.5) * (height / rows) - 0.5
        u = (torch.arange(-pad_cols, cols + pad_cols, **kwargs) + 0.5) * (width / cols) - 0.5
        v, u = torch.meshgrid(v, u, indexing="ij")
        rays = torch.stack([u, v, torch.ones_like(u)], dim=-1) @ torch.linalg.inv(self.intrinsics).T  # camera z = 1
        camera = self.depths()[:, None, None, None] * rays  # [D, h', w', 3]
        return camera @ self.c2w[:3, :3].T + self.c2w[:3, 3]

    def coordinates(self, points: Tensor) -> Tensor:
        """MVSNeRF's normalised reference coordinates ``[N, 3]`` of world points ``[N, 3]``.

        x and y run from 0 to 1 across the reference image (0 and 1 are its edges), z from 0 at ``near`` to 1 at ``far``
        (linear in depth, or in 1/depth with ``inverse_depth``); all three are unbounded outside the frustum. A point
        at or behind the reference camera's plane gets x = y = -1 (outside the image).
        """
        height, width = self.image_size
        w2c = world_to_camera(self.c2w[None])[0]
        camera = points @ w2c[:3, :3].T + w2c[:3, 3]
        depth = camera[:, 2]
        ahead = depth > MIN_DEPTH
        pixels = (camera @ self.intrinsics.T)[:, :2] / torch.where(ahead, depth, torch.ones_like(depth))[:, None]
        xy = (pixels + 0.5) / torch.tensor([width, height], dtype=points.dtype, device=points.device)
        xy = torch.where(ahead[:, None], xy, torch.full_like(xy, -1.0))
        if self.inverse_depth:
            z = (1.0 / torch.where(ahead, depth, torch.full_like(depth, MIN_DEPTH)) - 1.0 / self.near) / (
                1.0 / self.far - 1.0 / self.near)
        else:
            z = (depth - self.near) / (self.far - self.near)
        return torch.cat([xy, z[:, None]], dim=-1)

    def sample(self, volume: Tensor, coordinates: Tensor) -> Tensor:
        """Trilinear samples ``[N, C]`` of ``volume`` ``[C, D, h', w']`` at normalised ``coordinates`` ``[N, 3]`` (as
        ``coordinates`` returns them); zero outside the volume, blending to zero over its outermost voxel."""
        planes, rows, cols = self.volume_size
        if tuple(volume.shape[1:]) != (planes, rows, cols):
            raise ValueError(f"volume {list(volume.shape)} does not fit frustum volume size {[planes, rows, cols]}")
        # Voxel indices (a cell's centre is at index j; plane k at index k), then align_corners=True coordinates.
        col = coordinates[:, 0] * self.cells[1] - 0.5 + self.pad[1]
        row = coordinates[:, 1] * self.cells[0] - 0.5 + self.pad[0]
        plane = coordinates[:, 2] * (planes - 1)
        sizes = (cols, rows, planes)
        grid = torch.stack([2.0 * index / max(size - 1, 1) - 1.0 for index, size in zip((col, row, plane), sizes)], -1)
        sampled = F.grid_sample(volume[None], grid[None, :, None, None, :].to(volume.dtype), mode="bilinear",
                                padding_mode="zeros", align_corners=True)  # [1, C, N, 1, 1]
        return sampled[0, :, :, 0, 0].T


@dataclass(frozen=True)
class PlaneSweep:
    """Where each voxel centre of a ``ReferenceFrustum`` lands in V views.

    Attributes:
        grid: ``[V, D, h', w', 2]`` ``grid_sample`` coordinates in each view (``align_corners=False``).
        inside: ``[V, D, h', w']`` bool: the voxel centre is in front of the view and inside its image.
    """

    grid: Tensor
    inside: Tensor

    def warp(self, maps: Tensor) -> Tensor:
        """``[V, C, h_m, w_m]`` maps of the V views (any resolution that tiles their images) onto the planes:
        ``[V, C, D, h', w']``, bilinear, zero where a voxel projects outside a view."""
        views, planes, rows, cols, _ = self.grid.shape
        warped = F.grid_sample(maps, self.grid.reshape(views, planes, rows * cols, 2).to(maps.dtype), mode="bilinear",
                               padding_mode="zeros", align_corners=False)  # [V, C, D, h' w']
        warped = warped.reshape(views, maps.shape[1], planes, rows, cols)
        return warped * self.inside[:, None].to(warped.dtype)

    @property
    def count(self) -> Tensor:
        """``[D, h', w']`` float: how many views see each voxel."""
        return self.inside.sum(dim=0).to(self.grid.dtype)


def plane_sweep(frustum: ReferenceFrustum, intrinsics: Tensor, c2w: Tensor) -> PlaneSweep:
    """Where the voxel centres of ``frustum`` land in V views (``[V, 3, 3]`` intrinsics at the frustum's image size,
    ``[V, 4, 4]`` c2w); the reference view itself may be one of them (its warp is then the identity)."""
    centres = frustum.voxel_centres()
    planes, rows, cols, _ = centres.shape
    grid, inside = points_in_views(centres.reshape(-1, 3), intrinsics, c2w, frustum.image_size)
    views = grid.shape[0]
    return PlaneSweep(grid.reshape(views, planes, rows, cols, 2), inside.reshape(views, planes, rows, cols))


def variance_over_views(warped: Tensor, inside: Tensor) -> Tensor:
    """MVSNet's cost: the variance over views of warped features ``[V, C, D, h', w']``, counting at each voxel only the
    views that see it (``inside`` ``[V, D, h', w']``), so the mean and variance are normalised by that count; 0 where
    no view sees the voxel. Returns ``[C, D, h', w']``."""
    mask = inside[:, None].to(warped.dtype)
    count = mask.sum(dim=0).clamp_min(1.0)
    mean = (warped * mask).sum(dim=0) / count
    return (((warped - mean) ** 2) * mask).sum(dim=0) / count
