"""Scenes and frames of a dataset, loaded once and cached, and the source views of a target."""

from __future__ import annotations

from collections import OrderedDict
from typing import Sequence

import torch

from gpnerf_core.errors import DataError
from gpnerf_core.data.dataset import SceneDataset
from gpnerf_core.interfaces import ViewSelector
from gpnerf_core.types import Frame, Scene, SourceViews, TargetCamera


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
            if not torch.isfinite(scene.c2w).all():
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
        )

    def camera(self, scene: Scene, frame: Frame) -> TargetCamera:
        """The camera of ``frame`` (a frame of ``scene``) as a target, on the device."""
        return TargetCamera(
            intrinsics=frame.intrinsics.to(self.device),
            c2w=frame.c2w.to(self.device),
            height=frame.height,
            width=frame.width,
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
