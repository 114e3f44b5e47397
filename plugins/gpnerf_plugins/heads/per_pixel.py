"""The ``per_pixel`` head: a per-pixel MLP, the "label rendering" baseline without spatial context."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor, nn

from gpnerf_core import ConfigError
from gpnerf_plugins.heads.base import ResizingHead


@dataclass
class PerPixelHeadConfig:
    """Options of the ``per_pixel`` head."""

    name: str = "per_pixel"
    """Registry name of the head."""
    hidden_dim: int = 128
    """Width of the hidden layers."""
    hidden_layers: int = 1
    """Hidden layers (1x1 conv + ReLU) before the classifier; 0 gives a linear classifier."""


class PerPixelHead(ResizingHead):
    """Classifies every cell of the feature map from its own feature only (1x1 convs), then resizes.

    Args:
        in_dim, in_levels, num_outputs: runtime sizes (see ``ResizingHead``); the levels are not used.
        hidden_dim: hidden width.
        hidden_layers: number of hidden layers.
    """

    def __init__(
        self, in_dim: int, in_levels: int, num_outputs: int, hidden_dim: int = 128, hidden_layers: int = 1
    ) -> None:
        super().__init__(in_dim, in_levels, num_outputs)
        if hidden_layers < 0:
            raise ConfigError(f"head.hidden_layers={hidden_layers}: expected 0 or more")
        if hidden_layers > 0 and hidden_dim < 1:
            raise ConfigError(f"head.hidden_dim={hidden_dim}: expected a positive integer")
        layers: list[nn.Module] = []
        width = in_dim
        for _ in range(hidden_layers):
            layers += [nn.Conv2d(width, hidden_dim, 1), nn.ReLU()]
            width = hidden_dim
        layers.append(nn.Conv2d(width, num_outputs, 1))
        self.mlp = nn.Sequential(*layers)

    def decode(self, features: Tensor) -> Tensor:
        """``[N, in_dim, h, w]`` -> ``[N, K, h, w]``."""
        return self.mlp(features)
