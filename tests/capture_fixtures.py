"""Captures in nerfstudio's transforms.json format written from embedded scenes, for the capture tests."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.calibration import undistort_points
from PIL import Image

from gpnerf_core.types import Scene
from gpnerf_plugins.datasets.embedded import CLASS_NAMES, IGNORE_INDEX

OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def distort_image(image: np.ndarray, k: np.ndarray, distortion: tuple[float, ...], nearest: bool) -> np.ndarray:
    """What a lens with OpenCV ``distortion`` would have recorded of the pinhole ``image`` (same K, same size).

    Each recorded pixel shows the scene point whose undistorted position kornia's ``undistort_points`` gives.
    """
    height, width = image.shape[:2]
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    recorded = torch.from_numpy(np.stack([u, v], -1).reshape(-1, 2))
    ideal = undistort_points(recorded, torch.from_numpy(k), torch.tensor(distortion, dtype=torch.float64),
                             num_iters=50).numpy()  # converged where the lens bends most
    ideal = ideal.reshape(height, width, 2)
    if nearest:
        x = np.clip(np.rint(ideal[..., 0]), 0, width - 1).astype(int)
        y = np.clip(np.rint(ideal[..., 1]), 0, height - 1).astype(int)
        return image[y, x]
    planar = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    grid = torch.from_numpy(ideal / [(width - 1) / 2, (height - 1) / 2] - 1).float()[None]
    out = torch.nn.functional.grid_sample(planar, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[0].permute(1, 2, 0).numpy()


def write_capture(scene: Scene, folder: Path, *, distortion: tuple[float, ...] | None = None,
                  per_frame_intrinsics: bool = False, labels: bool = True, depth: bool = True,
                  extra: dict | None = None) -> Path:
    """Write ``scene`` as a nerfstudio capture in ``folder``: PNG images, 16-bit depth in mm, class-id PNGs and
    classes.json, OpenGL camera-to-world matrices, COLMAP's pixel-centre convention (cx + 0.5). Returns the folder."""
    folder.mkdir(parents=True, exist_ok=True)
    for sub in ("images", "depths", "semantics"):
        (folder / sub).mkdir(exist_ok=True)
    k = scene.intrinsics[0].double().numpy()
    top: dict = {"camera_model": "OPENCV" if distortion else "PINHOLE", "w": scene.width, "h": scene.height}
    intrinsics = {"fl_x": k[0, 0], "fl_y": k[1, 1], "cx": k[0, 2] + 0.5, "cy": k[1, 2] + 0.5}
    if distortion:
        intrinsics.update(dict(zip(("k1", "k2", "p1", "p2"), distortion)))
    if not per_frame_intrinsics:
        top.update(intrinsics)
    frames = []
    for index in range(scene.num_frames):
        frame = scene.load_frame(index)
        name = f"frame_{index:05d}"
        rgb = frame.rgb.numpy()
        semantic = frame.semantic.numpy().astype(np.uint8)
        depth_mm = np.rint(frame.depth.numpy() * 1000).astype(np.uint16)
        if distortion:
            rgb = distort_image(rgb, k, distortion, nearest=False)
            semantic = distort_image(semantic, k, distortion, nearest=True)
            depth_mm = distort_image(depth_mm, k, distortion, nearest=True)
        Image.fromarray(np.rint(rgb * 255).astype(np.uint8)).save(folder / "images" / f"{name}.png")
        entry = {"file_path": f"images/{name}.png",
                 "transform_matrix": (frame.c2w.double().numpy() @ OPENGL).tolist()}
        if per_frame_intrinsics:
            entry.update(intrinsics)
        if depth:
            Image.fromarray(depth_mm).save(folder / "depths" / f"{name}.png")
            entry["depth_file_path"] = f"depths/{name}.png"
        if labels:
            Image.fromarray(semantic).save(folder / "semantics" / f"{name}.png")
            entry["semantic_file_path"] = f"semantics/{name}.png"
        frames.append(entry)
    top["frames"] = frames
    top.update(extra or {})
    (folder / "transforms.json").write_text(json.dumps(top, indent=1))
    if labels:
        (folder / "classes.json").write_text(json.dumps({"classes": list(CLASS_NAMES), "ignore_index": IGNORE_INDEX}))
    return folder
