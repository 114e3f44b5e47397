"""A tiny in-memory dataset for the feature provider tests: smooth random textures (image-like: XFeat's descriptors
vary over them) at 96 x 128, frames decoded on demand, and a provider that counts its compute calls."""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F

from gpnerf_core import FeatureProvider, Frame, Scene, SceneDataset


class TinyScenes(SceneDataset):
    """``scenes`` scenes ``s0, s1, ...`` of ``frames`` frames each, ``height x width``; ``seed`` changes the pixels."""

    def __init__(self, frames: int = 10, height: int = 96, width: int = 128, seed: int = 0, scenes: int = 1) -> None:
        self.frames, self.height, self.width, self.seed, self.count = frames, height, width, seed, scenes
        self.loads = 0

    class_names = ("thing",)
    ignore_index = 255

    def scenes(self, split: str) -> tuple[str, ...]:
        return tuple(f"s{i}" for i in range(self.count)) if split == "train" else ()

    def load_scene(self, name: str) -> Scene:
        index = int(name[1:])

        def frame(i: int) -> Frame:
            self.loads += 1
            g = torch.Generator().manual_seed(self.seed * 100003 + index * 1009 + i)
            coarse = torch.rand(1, 3, self.height // 8, self.width // 8, generator=g)
            rgb = F.interpolate(coarse, size=(self.height, self.width), mode="bilinear", align_corners=False)[0]
            return Frame(rgb=rgb.permute(1, 2, 0).contiguous(), depth=torch.zeros(self.height, self.width),
                         semantic=torch.zeros(self.height, self.width, dtype=torch.long), intrinsics=torch.eye(3),
                         c2w=torch.eye(4))

        c2w = torch.eye(4).repeat(self.frames, 1, 1)
        c2w[:, 0, 3] = torch.arange(self.frames, dtype=torch.float32) * 0.1
        return Scene(name=name, c2w=c2w, intrinsics=torch.eye(3).repeat(self.frames, 1, 1), height=self.height,
                     width=self.width, near=0.1, far=5.0, train_frames=tuple(range(self.frames)), eval_frames=(),
                     load_frame=frame)


class CountingProvider(FeatureProvider):
    """Mean colour per 8 x 8 cell and its square (6 channels), scaled by ``scale``; counts the frames computed."""

    channels, stride = 6, 8

    def __init__(self, scale: float = 1.0) -> None:
        self.scale = scale
        self.frames: list[int] = []

    def fingerprint(self) -> str:
        return f"counting|scale {self.scale}"

    def compute(self, scene: str, frames: Sequence[int], images: torch.Tensor) -> torch.Tensor:
        self.frames.extend(frames)
        cells = F.avg_pool2d(images, self.stride)
        return torch.cat([cells, cells**2], dim=1) * self.scale
