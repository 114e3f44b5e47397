"""Shared input checks and output resizing of the built-in perception heads."""

from __future__ import annotations

from abc import abstractmethod

import torch.nn.functional as F
from torch import Tensor

from gpnerf_core import ConfigError, HeadOutput, PerceptionHead


class ResizingHead(PerceptionHead):
    """A head that decodes at the feature map's resolution and resizes its logits to the requested size.

    Subclasses implement ``decode``; ``forward`` checks the input and resizes bilinearly with
    align_corners=True (corner pixels map to corner cells, as GP-NeRF's final upsampling does), so any map
    size and any output size work.

    Args:
        in_dim: channels of the input map (C_sem).
        in_levels: equal channel blocks of the input map, finest first.
        num_outputs: K, channels of the logits.
    """

    def __init__(self, in_dim: int, in_levels: int, num_outputs: int) -> None:
        super().__init__()
        if in_dim < 1 or in_levels < 1:
            raise ConfigError(
                f"head got in_dim={in_dim}, in_levels={in_levels}: it needs a semantic feature map "
                f"(is the extractor's semantic branch off?)"
            )
        if in_dim % in_levels:
            raise ConfigError(f"head in_dim={in_dim} is not divisible into in_levels={in_levels} equal blocks")
        if num_outputs < 1:
            raise ConfigError(f"head num_outputs={num_outputs}: expected a positive number of classes or slots")
        self.in_dim = int(in_dim)
        self.in_levels = int(in_levels)
        self._num_outputs = int(num_outputs)

    @property
    def num_outputs(self) -> int:
        return self._num_outputs

    @abstractmethod
    def decode(self, features: Tensor) -> Tensor:
        """``[N, in_dim, h, w]`` -> logits ``[N, K, h', w']`` at any resolution."""

    def forward(self, features: Tensor, output_size: tuple[int, int]) -> HeadOutput:
        """Decode ``features`` ``[N, in_dim, h, w]`` into logits ``[N, K, *output_size]``."""
        if features.dim() != 4 or features.shape[1] != self.in_dim:
            raise ConfigError(
                f"head input has shape {tuple(features.shape)}; "
                f"expected [N, {self.in_dim}, h, w] (in_dim={self.in_dim})"
            )
        size = (int(output_size[0]), int(output_size[1]))
        if min(size) < 1:
            raise ConfigError(f"head output_size={tuple(output_size)}: expected two positive integers")
        logits = self.decode(features)
        if tuple(logits.shape[-2:]) != size:
            logits = F.interpolate(logits, size=size, mode="bilinear", align_corners=True)
        return HeadOutput(logits=logits)
