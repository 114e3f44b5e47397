"""Building the ``mvsnerf`` family from its options and the configured feature extractor."""

from __future__ import annotations

from typing import Sequence

from gpnerf_core import ConfigError, ModelParts, SurfaceSampling
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
    sampler: str = MVSNeRFConfig.sampler,
    surface_spread: float = MVSNeRFConfig.surface_spread,
    surface_uncertainty: float = MVSNeRFConfig.surface_uncertainty,
) -> MVSNeRF:
    """The extractor the config selects (``feature_extractor=mvsnet`` for MVSNeRF's) and the family's own networks.

    Without a ``+head`` the semantic branch renders class scores (label rendering). With one it renders features in the
    extractor's semantic-map space for the head to decode (GP-NeRF's context-aware decoding), which needs an extractor
    with semantic maps (``resunet_fpn``; its radiance maps then build the cost volume in place of FeatureNet's): a head
    with one that has none (``mvsnet``) is refused in one line."""
    pad = [int(value) for value in pad]
    if len(pad) != 2:
        raise ConfigError(f"model.pad={pad}: expected [rows, columns], two cell counts")
    sampling = SurfaceSampling(sampler, surface_spread, surface_uncertainty)
    depth_source = parts.one_pass_depth_source("mvsnerf", sampler, fine_samples)
    extractor = parts.build("feature_extractor")
    head = parts.semantic_head(extractor, "mvsnerf")
    return MVSNeRF(
        extractor=extractor,
        head=head,
        num_classes=parts.num_classes if label_rendering else 0,
        coarse_samples=coarse_samples,
        fine_samples=fine_samples,
        volume_views=volume_views,
        num_planes=num_planes,
        inverse_depth=inverse_depth,
        pad=(pad[0], pad[1]),
        width=width,
        sampling=sampling,
        depth_source=depth_source,
    )
