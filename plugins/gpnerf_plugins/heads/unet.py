"""The ``unet`` head: GP-NeRF's context-aware decoder over the 4 levels of the semantic map."""

from __future__ import annotations

from dataclasses import dataclass

import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import ConfigError
from gpnerf_plugins.heads.base import ResizingHead

DECODERS = ("unet", "semantic_fpn")


@dataclass
class UNetHeadConfig:
    """Options of the ``unet`` head."""

    name: str = "unet"
    """Registry name of the head."""
    decoder: str = "unet"
    """'unet': the paper's top-down U-Net form; 'semantic_fpn': the released code's Semantic-FPN decoder."""
    channels: int = 128
    """Width of every decoder conv (GP-NeRF: 128)."""
    norm_groups: int = 32
    """GroupNorm groups; must divide ``channels`` (GP-NeRF: 32)."""


def split_levels(features: Tensor, levels: int) -> list[Tensor]:
    """Undo the extractor's level concatenation.

    ``[N, L * C, h, w]`` -> L maps ``[N, C, ceil(h / 2^k), ceil(w / 2^k)]``, finest first. Bilinear
    resampling with align_corners=True keeps the extractor's corner-aligned geometry (the round trip is
    exact for features that vary linearly across the image).
    """
    height, width = features.shape[-2:]
    out = []
    for k, chunk in enumerate(features.chunk(levels, dim=1)):
        size = (-(-height // 2**k), -(-width // 2**k))
        out.append(chunk if k == 0 else F.interpolate(chunk, size=size, mode="bilinear", align_corners=True))
    return out


def _upsample(x: Tensor, size: tuple[int, ...]) -> Tensor:
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False)


def _msra_init(conv: nn.Conv2d) -> nn.Conv2d:
    nn.init.kaiming_normal_(conv.weight, mode="fan_out", nonlinearity="relu")
    if conv.bias is not None:
        nn.init.zeros_(conv.bias)
    return conv


class ConvGNReLU(nn.Sequential):
    """3x3 conv (no bias), GroupNorm, ReLU."""

    def __init__(self, in_channels: int, out_channels: int, groups: int) -> None:
        super().__init__(
            _msra_init(nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False)),
            nn.GroupNorm(groups, out_channels),
            nn.ReLU(),
        )


class UNetDecoder(nn.Module):
    """The paper's form, coarsest level first: s'_L = ReLU(GN(Conv(s_L))), then
    s'_k = ReLU(GN(Conv(P_k(s_k) + UpConv(s'_{k+1})))) down to the finest level.

    UpConv is a bilinear upsampling to level k's size followed by a 3x3 conv; P_k is a 1x1 projection to
    ``channels`` when a level is narrower or wider than ``channels``, else the identity.
    """

    def __init__(self, level_dim: int, levels: int, channels: int, groups: int) -> None:
        super().__init__()
        self.top = ConvGNReLU(level_dim, channels, groups)
        self.laterals = nn.ModuleList(
            nn.Identity() if level_dim == channels else _msra_init(nn.Conv2d(level_dim, channels, 1))
            for _ in range(levels - 1)
        )
        self.up_convs = nn.ModuleList(
            _msra_init(nn.Conv2d(channels, channels, 3, padding=1)) for _ in range(levels - 1)
        )
        self.fuse = nn.ModuleList(ConvGNReLU(channels, channels, groups) for _ in range(levels - 1))

    def forward(self, levels: list[Tensor]) -> Tensor:
        """Levels finest first -> ``[N, channels, h_0, w_0]``."""
        x = self.top(levels[-1])
        for k in range(len(levels) - 2, -1, -1):
            up = self.up_convs[k](_upsample(x, levels[k].shape[-2:]))
            x = self.fuse[k](self.laterals[k](levels[k]) + up)
        return x


class SemanticFPNDecoder(nn.Module):
    """The released code's Semantic-FPN: level k goes through k [conv, GN, ReLU, x2 upsample] steps (one
    conv without upsampling for k = 0) to the finest grid, and the level maps are summed."""

    def __init__(self, level_dim: int, levels: int, channels: int, groups: int) -> None:
        super().__init__()
        self.scale_heads = nn.ModuleList(
            nn.ModuleList(ConvGNReLU(level_dim if j == 0 else channels, channels, groups) for j in range(max(1, k)))
            for k in range(levels)
        )

    def forward(self, levels: list[Tensor]) -> Tensor:
        """Levels finest first -> ``[N, channels, h_0, w_0]``."""
        sizes = [x.shape[-2:] for x in levels]
        total = None
        for k, (convs, x) in enumerate(zip(self.scale_heads, levels)):
            for j, conv in enumerate(convs):
                x = conv(x)
                if k > 0:
                    x = _upsample(x, sizes[k - 1 - j])
            total = x if total is None else total + x
        return total


class UNetHead(ResizingHead):
    """Context-aware perception head: split the map into its levels, decode top-down, classify, resize.

    Args:
        in_dim, in_levels, num_outputs: runtime sizes (see ``ResizingHead``).
        decoder: one of ``DECODERS``.
        channels: decoder width.
        norm_groups: GroupNorm groups, a divisor of ``channels``.
    """

    def __init__(
        self,
        in_dim: int,
        in_levels: int,
        num_outputs: int,
        decoder: str = "unet",
        channels: int = 128,
        norm_groups: int = 32,
    ) -> None:
        super().__init__(in_dim, in_levels, num_outputs)
        if decoder not in DECODERS:
            raise ConfigError(f"head.decoder={decoder!r}: expected one of {', '.join(DECODERS)}")
        if channels < 1:
            raise ConfigError(f"head.channels={channels}: expected a positive integer")
        if norm_groups < 1 or channels % norm_groups:
            raise ConfigError(f"head.norm_groups={norm_groups} does not divide head.channels={channels}")
        self.decoder_kind = decoder
        body = UNetDecoder if decoder == "unet" else SemanticFPNDecoder
        self.decoder = body(in_dim // in_levels, in_levels, channels, norm_groups)
        self.predictor = _msra_init(nn.Conv2d(channels, num_outputs, 1))

    def decode(self, features: Tensor) -> Tensor:
        """``[N, in_dim, h, w]`` -> ``[N, K, h, w]``."""
        return self.predictor(self.decoder(split_levels(features, self.in_levels)))
