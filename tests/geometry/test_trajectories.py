"""Camera trajectories for ``render``: quaternion round trips, interpolation through key poses, the spiral."""

import math

import pytest
import torch

from gpnerf_core.geometry.trajectories import (
    interpolate_poses,
    quaternion_to_rotation,
    rotation_to_quaternion,
    spiral_poses,
)


def rotation(axis, angle):
    axis = torch.tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def pose(axis, angle, position):
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3], out[:3, 3] = rotation(axis, angle), torch.tensor(position, dtype=torch.float64)
    return out


@pytest.mark.parametrize("axis,angle", [((0, 0, 1), 0.3), ((1, 1, 0), 2.9), ((0.2, -1, 0.5), 3.1), ((1, 0, 0), 0.0)])
def test_quaternions_round_trip(axis, angle):
    r = rotation(axis, angle)
    assert torch.allclose(quaternion_to_rotation(rotation_to_quaternion(r)), r, atol=1e-9)


def test_interpolation_passes_through_the_keys_with_rigid_poses():
    keys = torch.stack([pose((0, 1, 0), 0.0, (0, 0, 0)), pose((0, 1, 0), 1.0, (1, 0, 0)), pose((1, 0, 0), 0.5, (1, 2, 0))])
    poses = interpolate_poses(keys, 9)  # keys at 0, 4, 8
    for index, key in zip((0, 4, 8), keys):
        assert torch.allclose(poses[index], key, atol=1e-9)
    halfway = poses[2]
    assert torch.allclose(halfway[:3, :3], rotation((0, 1, 0), 0.5), atol=1e-9)  # slerp: half the angle
    assert torch.allclose(halfway[:3, 3], torch.tensor([0.5, 0, 0], dtype=torch.float64))
    for p in poses:
        assert torch.allclose(p[:3, :3] @ p[:3, :3].T, torch.eye(3, dtype=torch.float64), atol=1e-9)
        assert torch.isclose(torch.det(p[:3, :3]), torch.tensor(1.0, dtype=torch.float64))


def test_spiral_circles_the_centre_and_looks_at_the_focus_point():
    center = pose((0, 1, 0), 0.4, (1, 2, 3))
    target = center[:3, 3] + 2.0 * center[:3, 2]
    for p in spiral_poses(center, 8, radius=0.1, focus=2.0):
        assert torch.isclose((p[:3, 3] - center[:3, 3]).norm(), torch.tensor(0.1, dtype=torch.float64))
        to_target = (target - p[:3, 3]) / (target - p[:3, 3]).norm()
        assert torch.allclose(p[:3, 2], to_target, atol=1e-9)
        assert torch.isclose(torch.det(p[:3, :3]), torch.tensor(1.0, dtype=torch.float64))
