"""``teacher``: a trained checkpoint's own 2D features, its feature extractor's semantic map on the frame (the maps its
head decodes; the radiance map for an extractor without semantic maps), upsampled to one cell per ``stride`` pixels."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import ConfigError, FeatureProvider, trained_feature_extractor

MAPS = ("semantic", "radiance")


@dataclass
class TeacherProviderConfig:
    name: str = "teacher"
    """Registry name and Hydra option (+feature_provider=teacher)."""
    checkpoint: str = ""
    """The trained run's checkpoint (.pt) whose feature extractor gives the features."""
    map: str = "semantic"
    """Which of its maps: semantic (what its head decodes; falls back to radiance without one) or radiance."""
    stride: int = 4
    """Image pixels per feature cell: the map is resized (bilinear) to the frame's size over it."""
    normalise: bool = True
    """L2-normalise each cell's feature (cosine distillation and similarity queries compare directions)."""


class TeacherProvider(nn.Module, FeatureProvider):
    """The checkpoint's extractor, frozen: ``extractor(images).semantic`` (or ``.radiance``), bilinearly resized to
    ``feature_size``, optionally L2-normalised per cell."""

    def __init__(self, *, checkpoint: str, map: str, stride: int, normalise: bool) -> None:
        super().__init__()
        if not checkpoint:
            raise ConfigError("feature_provider.checkpoint is empty; expected a trained run's checkpoint (.pt) whose "
                              "feature extractor gives the features")
        if map not in MAPS:
            raise ConfigError(f"feature_provider.map={map!r}; expected one of: {', '.join(MAPS)}")
        if stride < 1:
            raise ConfigError(f"feature_provider.stride={stride}; expected a positive number of pixels per cell")
        self.extractor, family, identity = trained_feature_extractor(checkpoint, "feature_provider.checkpoint")
        self.map = map if map == "radiance" or self.extractor.semantic_dim else "radiance"
        self.channels = int(self.extractor.semantic_dim if self.map == "semantic" else self.extractor.radiance_dim)
        self.stride = int(stride)
        self.normalise = bool(normalise)
        weights = hashlib.sha256()
        for name, tensor in sorted(self.extractor.state_dict().items()):
            weights.update(name.encode() + tensor.detach().cpu().contiguous().numpy().tobytes())
        self._fingerprint = (f"teacher|{family}|{identity}|weights {weights.hexdigest()[:16]}|{self.map}|"
                             f"stride {stride}|normalise {self.normalise}")

    def fingerprint(self) -> str:
        return self._fingerprint

    def train(self, mode: bool = True) -> "TeacherProvider":
        return super().train(False)  # frozen: always in eval mode

    @torch.no_grad()
    def compute(self, scene: str, frames: Sequence[int], images: Tensor) -> Tensor:
        self.extractor.to(images.device)
        maps = self.extractor(images.float())
        features = maps.semantic if self.map == "semantic" else maps.radiance
        cells = self.feature_size(int(images.shape[-2]), int(images.shape[-1]))
        if tuple(features.shape[-2:]) != cells:
            features = F.interpolate(features, size=cells, mode="bilinear", align_corners=False)
        if self.normalise:
            features = F.normalize(features, dim=1)
        return features.float()
