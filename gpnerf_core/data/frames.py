"""Scenes and frames of a dataset, loaded once and cached, and the source views of a target."""

from __future__ import annotations

from collections import OrderedDict
from typing import Sequence

import torch
from torch import Tensor

from gpnerf_core.errors import DataError
from gpnerf_core.data.dataset import SceneDataset
from gpnerf_core.interfaces import ViewSelector
from gpnerf_core.types import Frame, Scene, SourceViews, TargetCamera
from gpnerf_core.runtime.finite import all_finite


class FrameCache:
    """A dataset's scenes (kept) and frames (least recently used evicted first), with source-view assembly.

    Args:
        dataset: the scene dataset.
        device: where ``source_views`` puts its tensors.
        max_cached_frames: frames kept decoded in memory.
    """

    def __init__(self, dataset: SceneDataset, device: torch.device, max_cached_frames: int = 512) -> None:
        self.dataset = dataset
        self.device = device
        self.max_cached_frames = max_cached_frames
        self._scenes: dict[str, Scene] = {}
        self._frames: OrderedDict[tuple[str, int], Frame] = OrderedDict()

    def scene(self, name: str) -> Scene:
        """The scene ``name``, loaded and checked on first use (finite poses, at least one training frame)."""
        if name not in self._scenes:
            scene = self.dataset.load_scene(name)
            if not all_finite(scene.c2w):
                raise DataError(f"scene {name!r}: camera poses contain NaN or Inf")
            if not scene.train_frames:
                raise DataError(f"scene {name!r} has no training frames to use as source views")
            self._scenes[name] = scene
        return self._scenes[name]

    def frame(self, scene: Scene, index: int) -> Frame:
        """Frame ``index`` of ``scene`` (CPU tensors)."""
        key = (scene.name, index)
        if key in self._frames:
            self._frames.move_to_end(key)
            return self._frames[key]
        frame = scene.load_frame(index)
        self._frames[key] = frame
        if len(self._frames) > self.max_cached_frames:
            self._frames.popitem(last=False)
        return frame

    def source_views(self, scene: Scene, indices: Sequence[int]) -> SourceViews:
        """The frames ``indices`` of ``scene`` as source views on the device."""
        frames = [self.frame(scene, i) for i in indices]
        return SourceViews(
            rgb=torch.stack([f.rgb.permute(2, 0, 1) for f in frames]).to(self.device),
            intrinsics=torch.stack([f.intrinsics for f in frames]).to(self.device),
            c2w=torch.stack([f.c2w for f in frames]).to(self.device),
            depth=torch.stack([f.depth for f in frames]).to(self.device),
            scene=scene.name,
            frames=tuple(int(i) for i in indices),
        )

    def camera(
        self,
        scene: Scene,
        frame: Frame | None = None,
        *,
        c2w: Tensor | None = None,
        intrinsics: Tensor | None = None,
        size: tuple[int, int] | None = None,
    ) -> TargetCamera:
        """A target camera in ``scene`` (its near and far), on the device: the camera of ``frame``, or a pose ``c2w``
        with ``frame``'s intrinsics and size (a trajectory's), or with ``intrinsics`` at ``size`` (the viewer's).

        The one place a ``TargetCamera`` is made for evaluation, ``render`` and the viewer.
        """
        if frame is None and (c2w is None or intrinsics is None or size is None):
            raise ValueError("camera() needs a frame, or c2w with intrinsics and size")
        height, width = size if size is not None else (frame.height, frame.width)
        return TargetCamera(
            intrinsics=(intrinsics if intrinsics is not None else frame.intrinsics).to(self.device),
            c2w=(c2w if c2w is not None else frame.c2w).float().to(self.device),
            height=int(height),
            width=int(width),
            near=scene.near,
            far=scene.far,
        )


def choose_sources(
    selector: ViewSelector,
    scene: Scene,
    target_index: int,
    num_views: int,
    generator: torch.Generator | None,
) -> list[int]:
    """Source frame indices for a target: drawn from the scene's training frames, never the target itself."""
    candidates = [i for i in scene.train_frames if i != target_index]
    if not candidates:
        raise DataError(f"scene {scene.name!r}: no candidate source views for frame {target_index}")
    positions = selector.select(scene.c2w[target_index], scene.c2w[candidates], num_views, generator)
    return [candidates[p] for p in positions]


def sources_at_pose(
    selector: ViewSelector, scene: Scene, c2w: torch.Tensor, num_views: int, exclude: int | None = None
) -> list[int]:
    """Source frame indices for a camera at ``c2w`` (a trajectory's pose, a viewer's camera): the scene's training
    frames but ``exclude`` (the frame the camera sits at, when it does) that the selector picks, deterministically."""
    candidates = [i for i in scene.train_frames if i != exclude] or list(scene.train_frames)
    positions = selector.select(c2w.detach().cpu().float(), scene.c2w[candidates], min(num_views, len(candidates)), None)
    return [candidates[p] for p in positions]
