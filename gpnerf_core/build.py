"""Builds components from a composed config through the registry, passing widths downstream."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gpnerf_core.errors import ConfigError
from gpnerf_core.interfaces import LossSet, SceneDataset, ViewSelector
from gpnerf_core.pipeline import GeneralizableNeRF
from gpnerf_core.registry import Registry, get_registry
from gpnerf_core.semantic_field import SemanticFieldRenderer


@dataclass
class Components:
    dataset: SceneDataset
    view_selector: ViewSelector
    model: GeneralizableNeRF
    loss: LossSet | None


def build_model(cfg: Any, num_classes: int, registry: Registry | None = None) -> GeneralizableNeRF:
    """Assemble the model; each stage's width comes from the stage before it."""
    registry = registry or get_registry()
    extractor = registry.build("feature_extractor", cfg.feature_extractor)
    field = registry.build("field_aggregator", cfg.field_aggregator, in_dim=3 + extractor.radiance_dim)
    ray = registry.build("ray_aggregator", cfg.ray_aggregator, in_dim=field.width, num_blocks=field.num_blocks)
    head = semantic = None
    wants_semantics = cfg.get("head") is not None and cfg.model.semantic_field.enabled
    if cfg.get("head") is not None:
        if extractor.semantic_dim == 0:
            raise ConfigError(
                f"head {cfg.head.name!r} needs semantic features but feature_extractor "
                f"{cfg.feature_extractor.name!r} produces none"
            )
        head = registry.build(
            "head",
            cfg.head,
            in_dim=extractor.semantic_dim,
            in_levels=extractor.semantic_levels,
            num_outputs=num_classes,
        )
    if wants_semantics:
        semantic = SemanticFieldRenderer(
            semantic_dim=extractor.semantic_dim,
            attention_channels=field.attention_channels,
            ray_heads=ray.num_heads,
            num_blocks=field.num_blocks,
            joint_attention=cfg.model.semantic_field.joint_attention,
            adaptor_relu=cfg.model.semantic_field.adaptor_relu,
        )
    return GeneralizableNeRF(
        extractor=extractor,
        field=field,
        ray=ray,
        head=head,
        semantic=semantic,
        coarse_samples=cfg.model.coarse_samples,
        fine_samples=cfg.model.fine_samples,
        detach_source_semantics=cfg.model.detach_source_semantics,
        fuse_rendered=cfg.train.fuse_rendered,
        checkpoint_blocks=cfg.model.checkpoint_blocks,
    )


def build_components(cfg: Any, registry: Registry | None = None) -> Components:
    registry = registry or get_registry()
    dataset = registry.build("dataset", cfg.dataset)
    selector = registry.build("view_selector", cfg.view_selector)
    model = build_model(cfg, dataset.num_classes, registry)
    loss = None
    if cfg.get("loss") is not None:
        loss = registry.build("loss", cfg.loss)
        if loss.needs_semantics and not model.has_semantics:
            raise ConfigError(
                f"loss {cfg.loss.name!r} needs semantics: add a head (+head=unet) and keep model.semantic_field.enabled=true"
            )
    return Components(dataset=dataset, view_selector=selector, model=model, loss=loss)
