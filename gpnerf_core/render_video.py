"""``python -m gpnerf_core render checkpoint=<.pt> [render.scene=...] [render.path=interpolate|spiral] [render.frames=N]``.

Renders a novel-view trajectory of one scene with a trained model: RGB, depth and the head's semantic classes side by
side per frame, written as PNG frames, an MP4 (imageio with its ffmpeg plugin) and a GIF in the run folder.

Trajectories (camera-to-world poses, OpenCV):
- ``interpolate``: through the poses of the scene's held-out frames (all frames if it has none) in order, rotations
  by spherical linear interpolation of quaternions, positions linearly.
- ``spiral``: around the pose of frame ``render.frame``: the camera centre moves on a circle of radius
  ``render.radius`` metres in its own image plane while looking at the point ``render.focus`` metres ahead.
Each rendered pose takes its source views from the scene's training frames with the configured view selector.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
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


def render_task_body(cfg: DictConfig, dist: Any) -> dict[str, Any]:
    import imageio.v2 as imageio
    from tqdm import tqdm

    from gpnerf_core.build import build_components
    from gpnerf_core.evaluation import visualize as vis
    from gpnerf_core.evaluation.instances import slot_predictions
    from gpnerf_core.frames import FrameCache
    from gpnerf_core.io import atomic_write_json
    from gpnerf_core.run import _prepare, _start, checkpoint_config
    from gpnerf_core.training.checkpoint import evaluation_weights, load_weights
    from gpnerf_core.types import TargetCamera

    checkpoint, state, notes = checkpoint_config(cfg, "render")
    _start(cfg)
    components = build_components(cfg)
    model = components.model
    load_weights(model, evaluation_weights(state, str(cfg.eval.weights))[0], f"checkpoint {checkpoint}")
    model.to(dist.device).eval()
    frames = FrameCache(components.dataset, dist.device)
    split_scenes = list(components.dataset.scenes("unseen")) + list(components.dataset.scenes("train"))
    name = str(cfg.render.scene) or (split_scenes[0] if split_scenes else "")
    if name not in split_scenes:
        raise ConfigError(f"render.scene={name!r} is not a scene of this dataset; known: {', '.join(split_scenes)}")
    scene = frames.scene(name)
    poses = trajectory(scene, cfg.render)
    reference = frames.frame(scene, scene.train_frames[0])
    candidates = list(scene.train_frames)
    count = min(int(cfg.model.num_source_views), len(candidates))
    folder, _ = _prepare(cfg, dist, resuming=False)
    run_dir = folder.path
    pictures = []
    with folder:
        for note in notes:
            print(f"note: {note}", file=sys.stderr)
        for pose in tqdm(poses, desc="render", unit="frame", file=sys.stderr, dynamic_ncols=True):
            c2w = pose.float()
            positions = components.view_selector.select(c2w, scene.c2w[candidates], count, None)
            sources = frames.source_views(scene, [candidates[p] for p in positions])
            camera = TargetCamera(
                intrinsics=reference.intrinsics.to(dist.device), c2w=c2w.to(dist.device),
                height=reference.height, width=reference.width, near=scene.near, far=scene.far,
            )
            prediction = model.predict(camera, sources, stride=int(cfg.eval.render_stride),
                                       chunk_rays=int(cfg.eval.chunk_rays))
            s = prediction.stride
            rgb = (prediction.rgb.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
            tiles = [np.kron(rgb, np.ones((s, s, 1), dtype=np.uint8)),
                     np.kron(vis.depth_to_color(prediction.depth.cpu(), scene.near, scene.far),
                             np.ones((s, s, 1), dtype=np.uint8))]
            labels = ["rgb", "depth"]
            if prediction.logits is not None and model.head.predicts == "instances":
                slots, _ = slot_predictions(prediction.logits[0].cpu())
                tiles.append(vis.colorize_instances(slots))  # a slot keeps its colour from frame to frame
                labels.append("instances")
            elif prediction.logits is not None:
                classes = prediction.logits[0].argmax(0).cpu()
                dataset = components.dataset
                tiles.append(vis.colorize_labels(classes, dataset.num_classes, dataset.ignore_index))
                labels.append("semantic")
            pictures.append(vis.side_by_side(tiles, labels))
        for index, picture in enumerate(pictures):
            vis.save_image(run_dir / "frames" / f"{index:04d}.png", picture)
        fps = int(cfg.render.fps)
        _write_video(imageio, run_dir / "trajectory.mp4", pictures, fps)
        _write_video(imageio, run_dir / "trajectory.gif", pictures, fps)
        result = {"checkpoint": str(checkpoint), "scene": name, "path": str(cfg.render.path), "frames": len(pictures),
                  "outputs": ["trajectory.mp4", "trajectory.gif", "frames/"]}
        atomic_write_json(run_dir / "render.json", result)
        print(f"rendered {len(pictures)} frames of {name} to {run_dir} (trajectory.mp4, trajectory.gif, frames/)")
    return result


def _write_video(imageio: Any, path: Path, pictures: list[np.ndarray], fps: int) -> None:
    """Write frames to ``path`` through a temporary name, so a failure leaves no half-written video."""
    temporary = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        if path.suffix == ".gif":
            imageio.mimsave(temporary, pictures, duration=1000 / max(fps, 1), loop=0)
        else:
            even = [p[: p.shape[0] // 2 * 2, : p.shape[1] // 2 * 2] for p in pictures]  # yuv420p needs even sides
            imageio.mimsave(temporary, even, fps=fps, codec="libx264", macro_block_size=1)
        temporary.replace(path)
    finally:
        temporary.unlink(missing_ok=True)
