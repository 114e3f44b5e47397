"""viser's camera <-> the framework's OpenCV camera: pose, quaternion and pinhole conversions."""

import math

import numpy as np
import pytest
import torch

from gpnerf_core.tools.viewer.camera import (
    rotation_from_wxyz,
    vertical_fov,
    view_from_viser,
    viser_pose,
    wxyz_from_rotation,
)


def _random_c2w(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = q, rng.normal(size=3)
    return c2w


def test_identity_quaternion_is_the_opencv_camera_axes():
    view = view_from_viser((1, 0, 0, 0), (1.0, 2.0, 3.0), fov=math.pi / 2, aspect=1.5, height=32, multiple=8)
    assert torch.equal(view.c2w[:3, :3], torch.eye(3))
    assert view.c2w[:3, 3].tolist() == [1.0, 2.0, 3.0]
    # 90 degrees vertical: focal = half the height; width = 48 (32 * 1.5, a multiple of 8); the principal point is
    # the image centre with pixel centres at integer coordinates (geometry.pixel_grid)
    assert (view.height, view.width) == (32, 48)
    assert view.intrinsics.tolist() == [[16.0, 0.0, 23.5], [0.0, 16.0, 15.5], [0.0, 0.0, 1.0]]


def test_a_quarter_turn_about_y_looks_along_world_x():
    half = math.sqrt(0.5)
    view = view_from_viser((half, 0, half, 0), (0, 0, 0), fov=1.0, aspect=1.0, height=16, multiple=4)
    forward = view.c2w[:3, 2]  # OpenCV: the camera looks along its +Z
    assert torch.allclose(forward, torch.tensor([1.0, 0.0, 0.0]), atol=1e-6)


@pytest.mark.parametrize("seed", range(6))
def test_pose_round_trip_through_viser(seed):
    c2w = _random_c2w(seed)
    wxyz, position = viser_pose(torch.from_numpy(c2w))
    assert wxyz[0] >= 0 and abs(np.linalg.norm(wxyz) - 1) < 1e-12
    assert np.allclose(rotation_from_wxyz(wxyz), c2w[:3, :3], atol=1e-10)
    intrinsics = torch.tensor([[40.0, 0, 23.5], [0, 40.0, 15.5], [0, 0, 1]])
    view = view_from_viser(wxyz, position, vertical_fov(intrinsics, 32), 48 / 32, 32, 8)
    assert torch.allclose(view.c2w, torch.from_numpy(c2w).float(), atol=1e-6)
    assert torch.allclose(view.intrinsics, intrinsics, atol=1e-4)


def test_rotations_near_half_turns_convert_stably():
    for axis in np.eye(3):
        rotation = 2 * np.outer(axis, axis) - np.eye(3)  # 180 degrees about the axis: trace -1
        assert np.allclose(rotation_from_wxyz(wxyz_from_rotation(rotation)), rotation, atol=1e-12)


def test_width_rounds_to_the_stride_multiple_and_bad_cameras_are_refused():
    assert view_from_viser((1, 0, 0, 0), (0, 0, 0), 1.0, 0.01, 32, 8).width == 8  # never below one cell
    assert view_from_viser((1, 0, 0, 0), (0, 0, 0), 1.0, 16 / 9, 32, 8).width == 56
    with pytest.raises(ValueError, match="not a rotation"):
        view_from_viser((0, 0, 0, 0), (0, 0, 0), 1.0, 1.0, 32, 8)
    with pytest.raises(ValueError, match="fov"):
        view_from_viser((1, 0, 0, 0), (0, 0, 0), 0.0, 1.0, 32, 8)
    with pytest.raises(ValueError, match="not finite"):
        view_from_viser((1, 0, 0, 0), (float("nan"), 0, 0), 1.0, 1.0, 32, 8)
