"""Interface of image encoders that feed the radiance and semantic fields."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor, nn

from gpnerf_core.interfaces.weights import ImportsWeights
from gpnerf_core.types import FeatureMaps


class FeatureExtractor(ImportsWeights, nn.Module, ABC):
    """Encodes images into a radiance feature map and, optionally, a multi-level semantic map.

    Built with plain keyword arguments from its config. Downstream stages read the widths below, so no
    width is ever repeated in a config.
    """

    @property
    @abstractmethod
    def radiance_dim(self) -> int:
        """Channels of ``FeatureMaps.radiance``."""

    @property
    def semantic_dim(self) -> int:
        """Channels of ``FeatureMaps.semantic`` (0 when the extractor has no semantic branch)."""
        return 0

    @property
    def semantic_levels(self) -> int:
        """Number of equal channel blocks (pyramid levels, finest first) in the semantic map."""
        return 0

    def check_image_size(self, height: int, width: int) -> None:
        """Raise ``ConfigError`` (one line, naming the size and what is expected) when images of ``height`` x
        ``width`` cannot be encoded; called before training or evaluation starts. By default any size can."""

    @abstractmethod
    def forward(self, images: Tensor) -> FeatureMaps:
        """Encode ``[N, 3, H, W]`` float images in [0, 1]; H and W must be divisible by 16."""
