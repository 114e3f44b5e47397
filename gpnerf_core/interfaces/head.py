"""Interface of perception heads that decode an image-level semantic feature map."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor, nn

from gpnerf_core.interfaces.weights import ImportsWeights
from gpnerf_core.types import HeadOutput


class PerceptionHead(ImportsWeights, nn.Module, ABC):
    """Turns a ``[N, C_sem, h, w]`` feature map into per-pixel scores.

    Constructed with ``in_dim`` (C_sem), ``in_levels`` (equal channel blocks, finest first) and
    ``num_outputs`` (classes, or instance slots), all supplied by the pipeline.
    """

    @property
    @abstractmethod
    def num_outputs(self) -> int:
        """K: channels of ``HeadOutput.logits``."""

    @abstractmethod
    def forward(self, features: Tensor, output_size: tuple[int, int]) -> HeadOutput:
        """Decode ``features`` and return logits ``[N, K, *output_size]``."""
