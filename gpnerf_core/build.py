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


def head_predicts(head_cfg: Any, registry: Registry) -> str:
    """What the head ``head_cfg`` names predicts (``PerceptionHead.predicts``): ``"classes"`` or ``"instances"``."""
    return str(getattr(registry.get("head", str(head_cfg["name"])).spec.factory, "predicts", "classes"))


def head_outputs(head_cfg: Any, num_classes: int, registry: Registry) -> int:
    """``num_outputs`` of a head: the dataset's classes, or ``slots + 1`` for an instance head."""
    if head_predicts(head_cfg, registry) != "instances":
        return num_classes
    slots = head_cfg.get("slots")
    if not isinstance(slots, int) or isinstance(slots, bool):
        raise ConfigError(
            f"head {head_cfg['name']!r} predicts instances, so its config needs head.slots, an integer; got {slots!r}"
        )
    return slots + 1  # the head itself checks the value


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
            num_outputs=head_outputs(cfg.head, num_classes, registry),
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
            hint = "+head=instance" if loss.head_predicts == "instances" else "+head=unet"
            raise ConfigError(
                f"loss {cfg.loss.name!r} needs semantics: add a head ({hint}) and keep "
                "model.semantic_field.enabled=true"
            )
        predicts = model.head.predicts if model.head is not None else None
        if loss.head_predicts is not None and predicts is not None and loss.head_predicts != predicts:
            wanted = "an instance head (+head=instance)" if loss.head_predicts == "instances" else "a class head"
            raise ConfigError(
                f"loss {cfg.loss.name!r} trains {loss.head_predicts} but head {cfg.head.name!r} predicts {predicts}; "
                f"use {wanted} or a loss set for {predicts} (+loss={'instance' if predicts == 'instances' else 'dgs'})"
            )
    return Components(dataset=dataset, view_selector=selector, model=model, loss=loss)
