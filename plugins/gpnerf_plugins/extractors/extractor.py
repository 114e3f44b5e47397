"""The ``resunet_fpn`` feature extractor: GNT's ResUNet for radiance plus GP-NeRF's FPN for semantics."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import torch.nn.functional as F
from torch import Tensor

from gpnerf_core import ConfigError, FeatureExtractor, FeatureMaps, ImportedWeights, fractions, size_knob
from gpnerf_plugins.extractors.fpn import FPN, concat_levels
from gpnerf_plugins.extractors.resunet import ResUNet

_STRIDE = 16  # coarsest encoder tap (x3): images are padded to a multiple of it
_MAP_STRIDE = 4  # the radiance map's stride: image sides must be multiples of it for the maps to tile the image
_LEVELS = 4  # x0..x3


@dataclass
class ResUNetFPNConfig:
    """Options of the ``resunet_fpn`` extractor."""

    name: str = "resunet_fpn"
    """Registry name of the extractor."""
    widths: list[int] = field(default_factory=lambda: [64, 64, 128, 256])
    """Channels of the stem, layer1, layer2 and layer3 (GNT's ResNet-34: 64, 64, 128, 256)."""
    blocks: list[int] = field(default_factory=lambda: [3, 4, 6])
    """BasicBlocks in layer1, layer2 and layer3 (ResNet-34: 3, 4, 6)."""
    radiance_dim: int = 32
    """Channels of the radiance map at 1/4 resolution (GNT: 32)."""
    detach_deep_for_radiance: bool = True
    """Feed x3 detached into the radiance decoder, so rendering never trains layer3 (GP-NeRF: True, GNT: False)."""
    semantic: bool = True
    """Build the FPN semantic branch; False gives a GNT-only extractor (no semantic map)."""
    fpn_channels: int = size_knob(128, "semantic width", fractions(4, 4, 0.75, 0.5), needs="head")
    """Channels of each of the 4 FPN levels; the semantic map has 4 times this many (GP-NeRF: 128); a size knob only
    with a ``+head``, the one reader of the semantic map."""


def _check_positive_list(key: str, values: Sequence[int], length: int) -> list[int]:
    values = [int(v) for v in values]
    if len(values) != length or any(v < 1 for v in values):
        raise ConfigError(f"model.feature_extractor.{key}={values}: expected {length} positive integers")
    return values


class ResUNetFPN(FeatureExtractor):
    """Shared encoder with a U-Net radiance decoder (1/4) and an optional concatenated FPN (1/2).

    ``forward`` returns ``FeatureMaps(radiance=[N, radiance_dim, H/4, W/4],
    semantic=[N, 4 * fpn_channels, H/2, W/2] or None)``; semantic channel block k holds FPN level k
    (stride 2^(k+1)), finest first. Input images are raw RGB in [0, 1] with H and W multiples of 4; the encoder
    needs multiples of 16, so images are padded (edge values) at the bottom and right and the maps cropped back to
    exactly H/4 x W/4 and H/2 x W/2 cells (120x160, the paper's half-resolution ScanNet, works).
    """

    def __init__(
        self,
        widths: Sequence[int] = (64, 64, 128, 256),
        blocks: Sequence[int] = (3, 4, 6),
        radiance_dim: int = 32,
        detach_deep_for_radiance: bool = True,
        semantic: bool = True,
        fpn_channels: int = 128,
    ) -> None:
        super().__init__()
        widths = _check_positive_list("widths", widths, 4)
        blocks = _check_positive_list("blocks", blocks, 3)
        if radiance_dim < 1:
            raise ConfigError(f"model.feature_extractor.radiance_dim={radiance_dim}: expected a positive integer")
        if semantic and fpn_channels < 1:
            raise ConfigError(f"model.feature_extractor.fpn_channels={fpn_channels}: expected a positive integer")
        self.backbone = ResUNet(widths, blocks, radiance_dim)
        self.fpn = FPN(widths, fpn_channels) if semantic else None
        self.detach_deep_for_radiance = bool(detach_deep_for_radiance)
        self._radiance_dim = int(radiance_dim)
        self._fpn_channels = int(fpn_channels) if semantic else 0

    @property
    def radiance_dim(self) -> int:
        return self._radiance_dim

    @property
    def semantic_dim(self) -> int:
        return _LEVELS * self._fpn_channels

    @property
    def semantic_levels(self) -> int:
        return _LEVELS if self.fpn is not None else 0

    def import_weights(self, checkpoint: Mapping[str, Any], fmt: str) -> ImportedWeights | None:
        """``fmt="gnt"``: an official GNT checkpoint's ``feature_net`` is the ResUNet (same names); no FPN."""
        state = checkpoint.get("feature_net") if fmt == "gnt" else None
        if not isinstance(state, Mapping):
            return None
        return ImportedWeights(
            {f"backbone.{key.removeprefix('module.')}": (f"feature_net.{key}", value) for key, value in state.items()}
        )

    def check_image_size(self, height: int, width: int) -> None:
        """H and W multiples of 4, at least 32."""
        # Reflect padding needs at least 2 cells at the coarsest tap, hence the 32-pixel minimum.
        if height % _MAP_STRIDE or width % _MAP_STRIDE or min(height, width) < 2 * _STRIDE:
            raise ConfigError(
                f"image size {height}x{width} (HxW) is not a multiple of {_MAP_STRIDE} of at least {2 * _STRIDE}, "
                f"which the resunet_fpn extractor needs (its maps have 1/{_MAP_STRIDE} and 1/2 of the image's cells); "
                "resize or crop the images"
            )

    def forward(self, images: Tensor) -> FeatureMaps:
        """Encode ``[N, 3, H, W]`` images in [0, 1] (H, W multiples of 4, at least 32)."""
        if images.dim() != 4 or images.shape[1] != 3:
            raise ConfigError(f"feature extractor input has shape {tuple(images.shape)}; expected [N, 3, H, W]")
        height, width = (int(side) for side in images.shape[-2:])
        self.check_image_size(height, width)
        pad_bottom, pad_right = -height % _STRIDE, -width % _STRIDE
        if pad_bottom or pad_right:
            images = F.pad(images, (0, pad_right, 0, pad_bottom), mode="replicate")
        x0, x1, x2, x3 = self.backbone.encode(images)
        deep = x3.detach() if self.detach_deep_for_radiance else x3
        radiance = self.backbone.decode(x1, x2, deep)
        semantic = concat_levels(self.fpn([x0, x1, x2, x3])) if self.fpn is not None else None
        if pad_bottom or pad_right:
            radiance = radiance[..., : height // _MAP_STRIDE, : width // _MAP_STRIDE]
            if semantic is not None:
                semantic = semantic[..., : height // 2, : width // 2]
        return FeatureMaps(radiance=radiance, semantic=semantic)
