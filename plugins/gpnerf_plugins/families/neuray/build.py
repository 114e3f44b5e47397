"""Building the ``neuray`` and ``semantic_ray`` families from their options and the configured parts."""

from __future__ import annotations

from gpnerf_core import ModelParts, SurfaceSampling
from gpnerf_plugins.families.neuray.config import NeuRayConfig
from gpnerf_plugins.families.neuray.model import VisibilityAwareRenderer


def _build(parts: ModelParts, name: str, cross_reprojection: bool, coarse_samples: int, fine_samples: int,
           visibility_dim: int, sampling: SurfaceSampling) -> VisibilityAwareRenderer:
    depth_source = parts.one_pass_depth_source(name, sampling.sampler, fine_samples)
    extractor = parts.build("feature_extractor")
    head = parts.semantic_head(extractor, name)
    return VisibilityAwareRenderer(extractor=extractor, num_classes=parts.num_classes, head=head,
                                   coarse_samples=coarse_samples, fine_samples=fine_samples,
                                   visibility_dim=visibility_dim, cross_reprojection=cross_reprojection,
                                   sampling=sampling, depth_source=depth_source)


def build_neuray(*, parts: ModelParts, coarse_samples: int = NeuRayConfig.coarse_samples,
                 fine_samples: int = NeuRayConfig.fine_samples,
                 visibility_dim: int = NeuRayConfig.visibility_dim, sampler: str = NeuRayConfig.sampler,
                 surface_spread: float = NeuRayConfig.surface_spread,
                 surface_uncertainty: float = NeuRayConfig.surface_uncertainty) -> VisibilityAwareRenderer:
    """NeuRay + semantic head: no Cross-Reprojection Attention."""
    return _build(parts, "neuray", False, coarse_samples, fine_samples, visibility_dim,
                  SurfaceSampling(sampler, surface_spread, surface_uncertainty))


def build_semantic_ray(*, parts: ModelParts, coarse_samples: int = NeuRayConfig.coarse_samples,
                       fine_samples: int = NeuRayConfig.fine_samples,
                       visibility_dim: int = NeuRayConfig.visibility_dim, sampler: str = NeuRayConfig.sampler,
                       surface_spread: float = NeuRayConfig.surface_spread,
                       surface_uncertainty: float = NeuRayConfig.surface_uncertainty) -> VisibilityAwareRenderer:
    """Semantic-Ray: with the Cross-Reprojection Attention."""
    return _build(parts, "semantic_ray", True, coarse_samples, fine_samples, visibility_dim,
                  SurfaceSampling(sampler, surface_spread, surface_uncertainty))
