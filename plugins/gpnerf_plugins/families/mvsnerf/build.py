"""Building the ``mvsnerf`` family from its options and the configured feature extractor."""

from __future__ import annotations

from typing import Sequence

from gpnerf_core import ConfigError, ModelParts
from gpnerf_plugins.families.mvsnerf.config import MVSNeRFConfig
from gpnerf_plugins.families.mvsnerf.model import MVSNeRF


def build_mvsnerf(
    *,
    parts: ModelParts,
    coarse_samples: int = MVSNeRFConfig.coarse_samples,
    fine_samples: int = MVSNeRFConfig.fine_samples,
    volume_views: int = MVSNeRFConfig.volume_views,
    num_planes: int = MVSNeRFConfig.num_planes,
    inverse_depth: bool = MVSNeRFConfig.inverse_depth,
    pad: Sequence[int] = (0, 0),
    width: int = MVSNeRFConfig.width,
    label_rendering: bool = MVSNeRFConfig.label_rendering,
) -> MVSNeRF:
    """The extractor the config selects (``feature_extractor=mvsnet`` for MVSNeRF's) and the family's own networks; a
    configured ``+head`` is refused (the family renders its class scores itself)."""
    if parts.configured("head"):
        raise ConfigError(f"+head={parts.name('head')}: model=mvsnerf renders class scores per pixel (label "
                          "rendering) and has no rendered feature map for a head to decode; drop +head")
    pad = [int(value) for value in pad]
    if len(pad) != 2:
        raise ConfigError(f"model.pad={pad}: expected [rows, columns], two cell counts")
    return MVSNeRF(
        extractor=parts.build("feature_extractor"),
        num_classes=parts.num_classes if label_rendering else 0,
        coarse_samples=coarse_samples,
        fine_samples=fine_samples,
        volume_views=volume_views,
        num_planes=num_planes,
        inverse_depth=inverse_depth,
        pad=(pad[0], pad[1]),
        width=width,
    )
