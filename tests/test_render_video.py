"""``render``: trajectories (interpolated, spiral) and the MP4 / GIF / PNG frames of a trained model."""

import json
import math
import os
import subprocess
import sys

import imageio.v2 as imageio
import pytest
import torch

from gpnerf_core.render_video import (
    interpolate_poses,
    quaternion_to_rotation,
    rotation_to_quaternion,
    spiral_poses,
)

TINY = [
    "dataset.height=32", "dataset.width=48", "dataset.frames_per_scene=6", "dataset.eval_every=3",
    "dataset.num_train_scenes=1", "feature_extractor.widths=[8,8,8,16]", "feature_extractor.fpn_channels=4",
    "field_aggregator.width=16", "field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2",
    "model.num_source_views=2", "train.rays=16", "threads=1", "eval.save_images=0",
]


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


def test_render_writes_mp4_gif_and_frames(tmp_path):
    env = dict(os.environ, GPNERF_CACHE=str(tmp_path / "cache"), GPNERF_DISABLE_PLUGIN_AUTOLOAD="1")

    def gpnerf(*args):
        return subprocess.run([sys.executable, "-m", "gpnerf_core", *args], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=600)

    base = gpnerf("run", "+head=unet", "+loss=dgs", *TINY, "train.steps=2", f"out_dir={tmp_path / 'base'}")
    assert base.returncode == 0, base.stderr[-2000:]
    checkpoint = tmp_path / "base" / "checkpoints" / "step_0000002.pt"
    result = gpnerf("render", f"checkpoint={checkpoint}", "render.frames=4", f"out_dir={tmp_path / 'video'}")
    assert result.returncode == 0, result.stderr[-2000:]
    video = tmp_path / "video"
    assert sorted(p.name for p in (video / "frames").iterdir()) == [f"{i:04d}.png" for i in range(4)]
    frame = imageio.imread(video / "frames" / "0000.png")
    assert frame.shape[1] > 3 * 48  # rgb, depth and semantics side by side
    assert len(imageio.mimread(video / "trajectory.gif")) == 4
    assert sum(1 for _ in imageio.get_reader(video / "trajectory.mp4")) == 4  # len() of an ffmpeg reader is inf
    assert json.loads((video / "render.json").read_text())["scene"] == "unseen_00"
    assert not list(video.glob(".*partial*"))
    bad = gpnerf("render", f"checkpoint={checkpoint}", "render.path=orbit", f"out_dir={tmp_path / 'bad'}")
    assert bad.returncode == 2 and bad.stderr.strip() == "error: render.path='orbit'; expected one of: interpolate, spiral"
    assert not (tmp_path / "bad").exists()
