"""Building the ``gnt`` family from its options and the configured parts."""

from __future__ import annotations

from typing import Any

from gpnerf_core import ConfigError, ModelParts, SurfaceSampling, checked_compile_backend
from gpnerf_plugins.families.gnt.config import GNTModelConfig, SemanticFieldConfig
from gpnerf_plugins.families.gnt.model import GeneralizableNeRF
from gpnerf_plugins.families.gnt.semantic_field import SemanticFieldRenderer


def build_gnt(
    *,
    parts: ModelParts,
    coarse_samples: int = GNTModelConfig.coarse_samples,
    fine_samples: int = GNTModelConfig.fine_samples,
    sampler: str = GNTModelConfig.sampler,
    surface_spread: float = GNTModelConfig.surface_spread,
    surface_uncertainty: float = GNTModelConfig.surface_uncertainty,
    detach_source_semantics: bool = GNTModelConfig.detach_source_semantics,
    semantic_field: SemanticFieldConfig | dict[str, Any] | None = None,
    fuse_rendered: bool = GNTModelConfig.fuse_rendered,
    checkpoint_blocks: bool = GNTModelConfig.checkpoint_blocks,
    channels_last_maps: bool = GNTModelConfig.channels_last_maps,
    compile: bool = GNTModelConfig.compile,
    compile_backend: str = GNTModelConfig.compile_backend,
) -> GeneralizableNeRF:
    """Extractor, field and ray aggregators, the head (if configured) and the semantic field (with a head, or with
    ``+feature_provider``: the feature field is its embedding projected to the provider's channels); each stage's
    width comes from the stage before it."""
    semantics = SemanticFieldConfig(**semantic_field) if isinstance(semantic_field, dict) else (
        semantic_field or SemanticFieldConfig())
    extractor = parts.build("feature_extractor")
    field = parts.build("field_aggregator", in_dim=3 + extractor.radiance_dim)
    ray = parts.build("ray_aggregator", in_dim=field.width, num_blocks=field.num_blocks)
    head = semantic = None
    feature_field = parts.feature_field()
    if feature_field is not None and extractor.semantic_dim == 0:
        raise ConfigError(f"+feature_provider={feature_field.name}: model=gnt renders its feature field from its "
                          f"semantic-embedding field, and feature_extractor {parts.name('feature_extractor')!r} makes "
                          "no semantic maps (model.feature_extractor.semantic=true, or another extractor)")
    if parts.configured("head"):
        if extractor.semantic_dim == 0:
            raise ConfigError(
                f"head {parts.name('head')!r} needs semantic features but feature_extractor "
                f"{parts.name('feature_extractor')!r} produces none"
            )
        head = parts.head(in_dim=extractor.semantic_dim, in_levels=extractor.semantic_levels)
    if (head is not None or feature_field is not None) and semantics.enabled:
        semantic = SemanticFieldRenderer(
            semantic_dim=extractor.semantic_dim,
            attention_channels=field.attention_channels,
            ray_heads=ray.num_heads,
            num_blocks=field.num_blocks,
            joint_attention=semantics.joint_attention,
            adaptor_relu=semantics.adaptor_relu,
        )
    depth_source = parts.depth_source(sampler)
    return GeneralizableNeRF(
        extractor=extractor,
        field=field,
        ray=ray,
        head=head,
        semantic=semantic,
        coarse_samples=coarse_samples,
        fine_samples=fine_samples,
        sampling=SurfaceSampling(sampler, surface_spread, surface_uncertainty),
        depth_source=depth_source,
        detach_source_semantics=detach_source_semantics,
        fuse_rendered=fuse_rendered,
        checkpoint_blocks=checkpoint_blocks,
        channels_last_maps=channels_last_maps,
        compile_backend=checked_compile_backend(compile_backend) if compile else None,
        feature_field=feature_field,
    )
