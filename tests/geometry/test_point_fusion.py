"""Rendered depth to points: back-projection, the multi-view agreement that drops what other views contradict, voxel
merging, and the PLY a viewer reads back."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from gpnerf_core.geometry.point_fusion import (
    DepthView, PointCloud, agreeing_views, backproject, conflicting_views, depth_agreement, free_space_conflict,
    voxel_merge,
)
from gpnerf_core.geometry.rays import pixel_grid
from gpnerf_core.runtime.ply import encode_ply, write_ply

HEIGHT, WIDTH, STRIDE = 24, 32, 2


def _camera(x: float) -> torch.Tensor:
    """An OpenCV camera at ``(x, 0, 0)`` looking along +z (the wall ``z = 3``)."""
    c2w = torch.eye(4)
    c2w[0, 3] = x
    return c2w


def _wall_view(x: float, wall_z: float = 3.0) -> DepthView:
    intrinsics = torch.tensor([[20.0, 0, (WIDTH - 1) / 2], [0, 20.0, (HEIGHT - 1) / 2], [0, 0, 1]])
    grid = (HEIGHT // STRIDE, WIDTH // STRIDE)
    return DepthView(depth=torch.full(grid, wall_z), pixels=pixel_grid(HEIGHT, WIDTH, STRIDE), intrinsics=intrinsics,
                     c2w=_camera(x), height=HEIGHT, width=WIDTH)


def test_backprojected_cells_lie_on_the_surface_and_project_back_to_their_pixels():
    view = _wall_view(0.5)
    points = backproject(view)
    assert points.shape == (HEIGHT * WIDTH // STRIDE**2, 3)
    assert torch.allclose(points[:, 2], torch.full_like(points[:, 2], 3.0))
    camera = points - view.c2w[:3, 3]
    pixels = (camera / camera[:, 2:]) @ view.intrinsics.T
    assert torch.allclose(pixels[:, :2], view.pixels, atol=1e-4)


def test_a_view_agrees_where_another_saw_the_same_surface_and_not_where_it_did_not():
    left, right = _wall_view(0.0), _wall_view(0.3)
    bumped = DepthView(**{**left.__dict__, "depth": left.depth.clone()})
    bumped.depth[4:8, 4:8] = 2.0  # a floater in front of the wall, in the left view only
    own = backproject(bumped)
    agree = depth_agreement(own, right, tolerance=0.01).reshape(bumped.depth.shape)
    assert not agree[4:8, 4:8].any()
    # the wall's cells agree where the right camera sees them: all but the first column (its image starts 0.3 m
    # further right) and the floater
    expected = torch.ones_like(agree)
    expected[:, 0] = False
    expected[4:8, 4:8] = False
    assert torch.equal(agree, expected)
    counts = agreeing_views([bumped, right, _wall_view(-0.3)], tolerance=0.01)
    assert [c.shape[0] for c in counts] == [bumped.depth.numel()] * 3
    assert int(counts[0].reshape(bumped.depth.shape)[4:8, 4:8].max()) == 0
    assert int(counts[0].max()) == 2


def test_points_behind_a_camera_or_outside_its_image_never_agree():
    view = _wall_view(0.0)
    behind = torch.tensor([[0.0, 0.0, -3.0], [50.0, 0.0, 3.0]])
    assert not depth_agreement(behind, view, tolerance=0.5).any()


def test_voxel_merge_means_positions_and_colours_and_votes_labels():
    xyz = torch.tensor([[0.01, 0.01, 0.01], [0.03, 0.01, 0.01], [0.02, 0.02, 0.02], [1.0, 1.0, 1.0]])
    rgb = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.5, 0.5, 0.5]])
    label = torch.tensor([4, 7, 7, 2])
    merged = voxel_merge(PointCloud(xyz, rgb, label), voxel=0.1)
    assert len(merged) == 2
    assert torch.allclose(merged.xyz[0], torch.tensor([0.02, 0.04 / 3, 0.04 / 3]))
    assert torch.allclose(merged.rgb[0], torch.full((3,), 1 / 3))
    assert merged.label.tolist() == [7, 2]
    assert voxel_merge(PointCloud(xyz, rgb, label), voxel=0.0) is not None and len(voxel_merge(
        PointCloud(xyz, rgb, label), voxel=0.0)) == 4


def test_the_ply_reads_back_in_trimesh_with_colours_and_the_label_property(tmp_path):
    xyz = np.array([[0, 0, 0], [1, 2, 3], [-1.5, 0.25, math.pi]], dtype=np.float32)
    colours = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], dtype=np.uint8)
    label = np.array([3, -1, 8], dtype=np.int32)
    path = write_ply(tmp_path / "points.ply", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": colours[:, 0],
                                                "green": colours[:, 1], "blue": colours[:, 2], "label": label},
                     comments=("made by a test",))
    cloud = trimesh.load(path)
    assert np.array_equal(np.asarray(cloud.vertices, dtype=np.float32), xyz)
    assert np.array_equal(np.asarray(cloud.colors)[:, :3], colours)
    assert np.array_equal(cloud.metadata["_ply_raw"]["vertex"]["data"]["label"], label)
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\ncomment made by a test\n")
    assert [p.name for p in tmp_path.iterdir()] == ["points.ply"]


def test_ply_refuses_ragged_columns_and_types_it_has_no_name_for():
    with pytest.raises(ValueError, match="differ in length"):
        encode_ply({"x": np.zeros(2, np.float32), "y": np.zeros(3, np.float32)})
    with pytest.raises(ValueError, match="'label' has dtype int64"):
        encode_ply({"label": np.zeros(2, np.int64)})


def test_a_floater_in_front_of_another_views_surface_is_seen_through_and_the_surface_is_not():
    left, right = _wall_view(0.0), _wall_view(0.3)
    bumped = DepthView(**{**left.__dict__, "depth": left.depth.clone()})
    bumped.depth[4:8, 4:8] = 2.0  # a floater 1 m in front of the wall, in the left view only
    seen_through = free_space_conflict(backproject(bumped), right, tolerance=0.05).reshape(bumped.depth.shape)
    expected = torch.zeros_like(seen_through)
    expected[4:8, 4:8] = True  # the right camera sees the wall behind it, so it sees through the floater
    assert torch.equal(seen_through, expected)
    behind = DepthView(**{**left.__dict__, "depth": torch.full_like(left.depth, 4.0)})  # a point behind the wall
    assert not free_space_conflict(backproject(behind), right, tolerance=0.05).any()  # occluded, not a conflict
    counts = conflicting_views([bumped, right, _wall_view(-0.3)], tolerance=0.05)
    assert int(counts[0].reshape(bumped.depth.shape)[4:8, 4:8].min()) == 2 and int(counts[1].max()) == 0
