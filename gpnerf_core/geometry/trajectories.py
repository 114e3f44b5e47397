"""Camera trajectories through a scene for novel-view rendering (``render``; camera-to-world poses, OpenCV):

- ``interpolate``: through the poses of the scene's held-out frames (all frames if it has none) in order, rotations
  by spherical linear interpolation of quaternions, positions linearly.
- ``spiral``: around the pose of frame ``render.frame``: the camera centre moves on a circle of radius
  ``render.radius`` metres in its own image plane while looking at the point ``render.focus`` metres ahead.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from omegaconf import DictConfig
from torch import Tensor

from gpnerf_core.errors import ConfigError

PATHS = ("interpolate", "spiral")


def rotation_to_quaternion(rotation: Tensor) -> Tensor:
    """``[3, 3]`` rotation -> unit quaternion ``[4]`` (w, x, y, z), w >= 0."""
    m = rotation.double()
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = torch.stack([1 + trace, 1 + m[0, 0] - m[1, 1] - m[2, 2], 1 - m[0, 0] + m[1, 1] - m[2, 2],
                              1 - m[0, 0] - m[1, 1] + m[2, 2]])
    k = int(torch.argmax(candidates))
    s = torch.sqrt(candidates[k].clamp_min(1e-12)) * 2  # 4 * |component k|
    if k == 0:
        q = torch.stack([s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif k == 1:
        q = torch.stack([(m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif k == 2:
        q = torch.stack([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s])
    else:
        q = torch.stack([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4])
    q = q / q.norm()
    return q if q[0] >= 0 else -q


def quaternion_to_rotation(q: Tensor) -> Tensor:
    """Unit quaternion ``[4]`` (w, x, y, z) -> ``[3, 3]`` rotation."""
    w, x, y, z = (q / q.norm()).tolist()
    return torch.tensor([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ], dtype=torch.float64)


def slerp(q0: Tensor, q1: Tensor, t: float) -> Tensor:
    """Spherical linear interpolation between unit quaternions (the shorter arc)."""
    dot = float(torch.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly parallel: linear is exact enough and stable
        q = q0 + t * (q1 - q0)
        return q / q.norm()
    angle = math.acos(dot)
    return (math.sin((1 - t) * angle) * q0 + math.sin(t * angle) * q1) / math.sin(angle)


def interpolate_poses(keys: Tensor, frames: int) -> Tensor:
    """``frames`` poses ``[frames, 4, 4]`` through the key poses ``[K, 4, 4]`` in order (first and last included)."""
    if keys.shape[0] == 1:
        return keys.double().expand(frames, 4, 4).clone()
    quaternions = [rotation_to_quaternion(k[:3, :3]) for k in keys]
    poses = []
    for i in range(frames):
        position = i * (keys.shape[0] - 1) / max(frames - 1, 1)
        a = min(int(position), keys.shape[0] - 2)
        t = position - a
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3] = quaternion_to_rotation(slerp(quaternions[a], quaternions[a + 1], t))
        pose[:3, 3] = (1 - t) * keys[a, :3, 3].double() + t * keys[a + 1, :3, 3].double()
        poses.append(pose)
    return torch.stack(poses)


def spiral_poses(center: Tensor, frames: int, radius: float, focus: float) -> Tensor:
    """``frames`` poses on a circle of ``radius`` metres in the image plane of ``center``, looking at the point
    ``focus`` metres in front of it (OpenCV axes: x right, y down, z forward)."""
    center = center.double()
    target = center[:3, 3] + focus * center[:3, 2]
    poses = []
    for i in range(frames):
        angle = 2 * math.pi * i / frames
        position = center[:3, 3] + radius * (math.cos(angle) * center[:3, 0] + math.sin(angle) * center[:3, 1])
        forward = target - position
        forward = forward / forward.norm()
        right = torch.linalg.cross(forward, -center[:3, 1])  # keep the original "up" (-y)
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, position
        poses.append(pose)
    return torch.stack(poses)


def trajectory(scene: Any, render: DictConfig) -> Tensor:
    """The poses ``[N, 4, 4]`` (float64) of ``render.path`` for ``scene``."""
    frames = int(render.frames)
    if frames < 1:
        raise ConfigError(f"render.frames={frames}: expected an integer >= 1")
    if render.path == "interpolate":
        keys = list(scene.eval_frames) or list(range(scene.c2w.shape[0]))
        return interpolate_poses(scene.c2w[keys], frames)
    if render.path == "spiral":
        index = int(render.frame)
        if not 0 <= index < scene.c2w.shape[0]:
            raise ConfigError(f"render.frame={index}: scene {scene.name!r} has frames 0..{scene.c2w.shape[0] - 1}")
        if float(render.radius) <= 0 or float(render.focus) <= 0:
            raise ConfigError(f"render.radius={render.radius}, render.focus={render.focus}: expected positive metres")
        return spiral_poses(scene.c2w[index], frames, float(render.radius), float(render.focus))
    raise ConfigError(f"render.path={render.path!r}; expected one of: {', '.join(PATHS)}")
