"""The ``separable`` head: a light context decoder of depthwise-separable convolutions over the semantic levels."""

from __future__ import annotations

from dataclasses import dataclass

import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import ConfigError, HeadOutput, PerceptionHead


@dataclass
class SeparableHeadConfig:
    """Options of the ``separable`` head (``+head=separable head.channels=32``)."""

    name: str = "separable"
    """Registry name: the Hydra option ``head/separable``."""
    channels: int = 64
    """Decoder width at every level."""
    kernel_size: int = 5
    """Depthwise kernel size (odd): the context one block adds at its level."""
    norm_groups: int = 8
    """GroupNorm groups; must divide ``channels``."""


class SeparableBlock(nn.Sequential):
    """Depthwise k x k conv, pointwise 1x1 conv, GroupNorm, ReLU: a k x k context for about 1/k^2 of a full conv."""

    def __init__(self, channels: int, kernel_size: int, groups: int) -> None:
        super().__init__(
            nn.Conv2d(channels, channels, kernel_size, padding=kernel_size // 2, groups=channels, bias=False),
            nn.Conv2d(channels, channels, 1, bias=False),
            nn.GroupNorm(groups, channels),
            nn.ReLU(),
        )


class SeparableHead(PerceptionHead):
    """Decodes the L semantic levels coarse to fine, classifies every cell and resizes to the requested size.

    The input ``[N, in_dim, h, w]`` holds L = ``in_levels`` equal channel blocks, finest first, all at h x w (the
    extractor upsampled the coarser ones). Level k is average-pooled back to ``ceil(h / 2^k) x ceil(w / 2^k)``,
    projected to ``channels`` and refined by a separable block; each result is upsampled and added into the next finer
    level before its block. A 1x1 classifier gives ``[N, K, h, w]``, resized bilinearly to ``output_size``.

    Args:
        in_dim, in_levels, num_outputs: from the pipeline (semantic width, levels, classes).
        channels, kernel_size, norm_groups: see ``SeparableHeadConfig`` (its defaults apply when built by name).
    """

    def __init__(
        self, *, in_dim: int, in_levels: int, num_outputs: int, channels: int, kernel_size: int, norm_groups: int
    ) -> None:
        super().__init__()
        if in_levels < 1 or in_dim % in_levels:
            raise ConfigError(f"head 'separable' got in_dim={in_dim} for in_levels={in_levels}: expected equal blocks")
        if num_outputs < 1:
            raise ConfigError(f"head 'separable' got num_outputs={num_outputs}: expected at least one class")
        if channels < 1 or norm_groups < 1 or channels % norm_groups:
            raise ConfigError(f"head.norm_groups={norm_groups} does not divide head.channels={channels}")
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ConfigError(f"head.kernel_size={kernel_size}: expected an odd positive size")
        self.in_dim, self.in_levels, self._num_outputs = in_dim, in_levels, num_outputs
        level_dim = in_dim // in_levels
        self.project = nn.ModuleList(nn.Conv2d(level_dim, channels, 1) for _ in range(in_levels))
        self.refine = nn.ModuleList(SeparableBlock(channels, kernel_size, norm_groups) for _ in range(in_levels))
        self.classify = nn.Conv2d(channels, num_outputs, 1)

    @property
    def num_outputs(self) -> int:
        return self._num_outputs

    def forward(self, features: Tensor, output_size: tuple[int, int]) -> HeadOutput:
        """``features [N, in_dim, h, w]`` -> ``HeadOutput(logits [N, K, *output_size])``."""
        if features.dim() != 4 or features.shape[1] != self.in_dim:
            raise ConfigError(
                f"head 'separable' got features {list(features.shape)}; expected [N, {self.in_dim}, h, w]"
            )
        height, width = features.shape[-2:]
        x = None
        for k, level in reversed(list(enumerate(features.chunk(self.in_levels, dim=1)))):
            size = (-(-height // 2**k), -(-width // 2**k))
            y = self.project[k](F.adaptive_avg_pool2d(level, size) if k else level)
            if x is not None:
                y = y + F.interpolate(x, size=size, mode="bilinear", align_corners=False)
            x = self.refine[k](y)
        logits = self.classify(x)
        size = (int(output_size[0]), int(output_size[1]))
        if tuple(logits.shape[-2:]) != size:
            logits = F.interpolate(logits, size=size, mode="bilinear", align_corners=False)
        return HeadOutput(logits=logits)
