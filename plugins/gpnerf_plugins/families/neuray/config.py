"""Options of the ``neuray`` and ``semantic_ray`` families (``model=neuray``, ``model=semantic_ray``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from gpnerf_core import ModelConfig, RayMarchingConfig, part
from gpnerf_plugins.families.rates import SourceViewRates


@dataclass
class NeuRayConfig(RayMarchingConfig):
    """NeuRay's visibility-aware renderer with Semantic-Ray's semantic head, without the Cross-Reprojection Attention
    ("NeuRay + Semantic Head" of GP-NeRF's Table 1)."""

    name: str = "neuray"
    """Registry name of this model family."""
    feature_extractor: Any = part("resunet_fpn")
    """Encodes the source views: image features (its radiance maps) and, for a ``+head``, semantic maps."""
    fine_samples: int = 24
    """Samples of the fine pass, drawn from the coarse pass's weights in normalised inverse depth; the fine pass
    renders only these (NeuRay and Semantic-Ray do not merge them with the coarse samples). 0 = coarse pass only."""
    visibility_dim: int = 32
    """Channels of the visibility feature map G of each source view (NeuRay: 32)."""
    sampler: str = "uniform"
    """``uniform``: NeuRay's two passes. ``depth`` (with ``+depth_source=<name>``, which it needs here): one pass through
    one network on ``fine_samples`` samples around the source views' depth of each ray, or spread by its belief where
    that depth is uncertain (``gpnerf_core.SurfaceSampling``; docs/rendering.md)."""
    surface_spread: float = 2.0
    """``sampler=depth``: the samples span the depth +- this many standard deviations of the belief."""
    surface_uncertainty: float = 0.2
    """``sampler=depth``: a ray whose belief's standard deviation exceeds this fraction of its depth gets its samples
    drawn from the belief."""
    lr: SourceViewRates = field(default_factory=SourceViewRates)
    """Learning rates (``model.lr.<group>``): ``feature_extractor``, ``transformer`` (the visibility decoder, the
    aggregation and density networks), ``head``."""

    runtime_keys: ClassVar[tuple[str, ...]] = ModelConfig.runtime_keys


@dataclass
class SemanticRayConfig(NeuRayConfig):
    """Semantic-Ray: NeuRay + semantic head with the Cross-Reprojection Attention on each sample's per-view features."""

    name: str = "semantic_ray"
    """Registry name of this model family."""
