import math

import pytest
import torch
from kornia.geometry.camera import unproject_points

from gpnerf_core.geometry import (
    importance_depths,
    pixel_grid,
    points_along_rays,
    project_points,
    rays_through_pixels,
    stratified_inverse_depths,
)
from gpnerf_core.geometry.projection import normalized_grid, world_to_camera


def look_at(eye, target):
    """OpenCV camera-to-world looking from eye to target, y down."""
    eye, target = torch.tensor(eye, dtype=torch.float32), torch.tensor(target, dtype=torch.float32)
    forward = (target - eye) / (target - eye).norm()
    down = torch.tensor([0.0, 0.0, -1.0])
    right = torch.linalg.cross(down, forward)
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    c2w = torch.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


def intrinsics(height=30, width=40, hfov=90.0):
    f = width / (2 * math.tan(math.radians(hfov) / 2))
    return torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], dtype=torch.float32)


def test_pixel_grid_stride_centres():
    grid = pixel_grid(4, 6, stride=2)
    assert grid.shape == (6, 2)
    assert torch.equal(grid[0], torch.tensor([0.5, 0.5]))
    assert torch.equal(grid[-1], torch.tensor([4.5, 2.5]))
    assert pixel_grid(3, 5).shape == (15, 2)


def test_ray_parameter_is_camera_depth_and_round_trip_with_kornia():
    K, c2w = intrinsics(), look_at([1.0, -2.0, 1.5], [0.0, 0.0, 0.3])
    pixels = torch.tensor([[0.0, 0.0], [39.0, 29.0], [19.5, 14.5], [7.0, 21.0]])
    depth = torch.tensor([0.5, 1.0, 2.0, 3.5])
    rays = rays_through_pixels(pixels, K, c2w, 0.1, 10.0)
    points = rays.origins + depth[:, None] * rays.directions
    cam = (world_to_camera(c2w[None])[0] @ torch.cat([points, torch.ones(4, 1)], -1).T).T[:, :3]
    assert torch.allclose(cam[:, 2], depth, atol=1e-5)
    # kornia's unprojection of the same pixels at the same depths lands on the same camera points
    assert torch.allclose(unproject_points(pixels, depth[:, None], K), cam, atol=1e-4)
    projected, z = project_points(points, K[None], c2w[None])
    assert torch.allclose(projected[0], pixels, atol=1e-3)
    assert torch.allclose(z[0], depth, atol=1e-5)


def test_projection_into_second_view_matches_its_own_rays():
    K = intrinsics()
    first, second = look_at([1.0, -2.0, 1.5], [0, 0, 0.3]), look_at([-1.5, -1.5, 1.0], [0, 0, 0.3])
    pixels = torch.tensor([[10.0, 5.0], [30.0, 25.0]])
    rays = rays_through_pixels(pixels, K, second, 0.1, 10.0)
    points = rays.origins + 2.0 * rays.directions
    projected, z = project_points(points, torch.stack([K, K]), torch.stack([first, second]))
    assert torch.allclose(projected[1], pixels, atol=1e-3)
    assert torch.allclose(z[1], torch.full((2,), 2.0), atol=1e-5)
    assert not torch.allclose(projected[0], pixels, atol=1.0)


def test_points_behind_camera_have_negative_depth():
    K, c2w = intrinsics(), look_at([0.0, -2.0, 0.0], [0, 0, 0])
    _, z = project_points(torch.tensor([[0.0, -4.0, 0.0]]), K[None], c2w[None])
    assert z.item() < 0


def test_normalized_grid_edges_independent_of_map_size():
    grid = normalized_grid(torch.tensor([[-0.5, -0.5], [39.5, 29.5], [19.5, 14.5]]), 30, 40)
    assert torch.allclose(grid, torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0]]))


def test_stratified_inverse_depth_sorted_bounded_and_denser_near():
    rays = rays_through_pixels(torch.zeros(5, 2), intrinsics(), torch.eye(4), 0.5, 8.0)
    det = stratified_inverse_depths(rays, 16, perturb=False)
    assert det.shape == (5, 16)
    assert torch.allclose(det[:, 0], torch.full((5,), 0.5)) and torch.allclose(det[:, -1], torch.full((5,), 8.0))
    inverse_steps = (1 / det).diff(dim=-1)
    assert torch.allclose(inverse_steps, inverse_steps[:, :1].expand_as(inverse_steps), atol=1e-5)
    g = torch.Generator().manual_seed(0)
    jittered = stratified_inverse_depths(rays, 16, perturb=True, generator=g)
    assert (jittered.diff(dim=-1) >= 0).all() and (jittered >= 0.5 - 1e-6).all() and (jittered <= 8.0 + 1e-6).all()
    assert not torch.allclose(jittered, det)
    again = stratified_inverse_depths(rays, 16, perturb=True, generator=torch.Generator().manual_seed(0))
    assert torch.equal(jittered, again)


def test_importance_samples_concentrate_on_heavy_weights():
    depths = torch.linspace(1.0, 5.0, 33).expand(4, 33).contiguous()
    weights = torch.zeros(4, 33)
    weights[:, 16] = 1.0  # all mass at depth 3.0
    fine = importance_depths(depths, weights, 64, deterministic=False, generator=torch.Generator().manual_seed(1))
    assert fine.shape == (4, 64)
    assert ((fine - 3.0).abs() < 0.2).float().mean() > 0.9
    det = importance_depths(depths, weights, 8, deterministic=True)
    assert torch.equal(det, importance_depths(depths, weights, 8, deterministic=True))
    assert not fine.requires_grad


def test_points_along_rays_sorts_depths():
    rays = rays_through_pixels(torch.tensor([[5.0, 5.0]]), intrinsics(), torch.eye(4), 0.1, 4.0)
    samples = points_along_rays(rays, torch.tensor([[3.0, 1.0, 2.0]]))
    assert torch.equal(samples.depths, torch.tensor([[1.0, 2.0, 3.0]]))
    assert torch.allclose(samples.points[0, :, 2], torch.tensor([1.0, 2.0, 3.0]))


@pytest.mark.parametrize("bad", [float("nan")])
def test_projection_propagates_nan_pose_as_invisible_or_nan(bad):
    c2w = torch.eye(4)
    c2w[0, 3] = bad
    pixels, z = project_points(torch.tensor([[0.0, 0.0, 1.0]]), intrinsics()[None], c2w[None])
    assert not torch.isfinite(z).all()  # callers validate poses up front (SceneViews), never train on this
