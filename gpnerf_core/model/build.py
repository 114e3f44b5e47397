"""Builds components from a composed config through the registry, passing widths downstream."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from gpnerf_core.errors import ConfigError
from gpnerf_core.data.dataset import SceneDataset
from gpnerf_core.interfaces import LossSet, ViewSelector
from gpnerf_core.model.pipeline import GeneralizableNeRF
from gpnerf_core.registry.components import Registry, get_registry
from gpnerf_core.model.semantic_field import SemanticFieldRenderer
from gpnerf_core.model.checkpoint import stored_classes


@dataclass(frozen=True)
class ClassList:
    """The classes a model's head predicts.

    Attributes:
        names: names of the class ids 0..K-1.
        ignore_index: the label value of unlabelled pixels in the labels the model was trained on.
        source: where the list came from, for notes (``"dataset 'embedded'"``, ``"checkpoint <path>"``).
        from_checkpoint: the list is a checkpoint's (the dataset has none).
    """

    names: tuple[str, ...]
    ignore_index: int
    source: str = "dataset"
    from_checkpoint: bool = False

    @property
    def num_classes(self) -> int:
        return len(self.names)

    def describe(self, shown: int = 6) -> str:
        """``9 classes of checkpoint <path> (wall, floor, ..., 3 more)``, for notes."""
        more = len(self.names) - shown
        names = ", ".join(self.names[:shown]) + (f", ... {more} more" if more > 0 else "")
        return f"{self.num_classes} classes of {self.source} ({names})"

    def note(self, dataset: str) -> str:
        """What a command says when dataset ``dataset`` has no class list and these (a checkpoint's) are used."""
        return f"dataset {dataset!r} has no class list: using the {self.describe()}"


def checkpoint_classes(state: Mapping[str, Any], path: str | Path) -> ClassList | None:
    """The classes a checkpoint stores (``stored_classes``) as a class list for a dataset without one; None for a
    checkpoint written before checkpoints kept them."""
    stored = stored_classes(state, path)
    return None if stored is None else ClassList(*stored, source=f"checkpoint {path}", from_checkpoint=True)


@dataclass
class Components:
    """What a config builds.

    Attributes:
        classes: the classes the model predicts (and evaluation scores, renders and names): the dataset's, or, for a
            dataset without a class list (a capture without labels), the checkpoint's the model was trained with.
    """

    dataset: SceneDataset
    view_selector: ViewSelector
    model: GeneralizableNeRF
    loss: LossSet | None
    classes: ClassList


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
        channels_last_maps=cfg.model.channels_last_maps,
        compile_backend=checked_compile_backend(cfg.model.compile_backend) if cfg.model.compile else None,
    )


def checked_compile_backend(backend: str) -> str:
    """``backend`` if ``torch.compile`` knows it; otherwise a ConfigError naming the key and the known ones."""
    import torch._dynamo

    known = sorted(torch._dynamo.list_backends(exclude_tags=()))
    if backend not in known:
        raise ConfigError(f"model.compile_backend={backend!r} is not a torch.compile backend; known: {', '.join(known)}")
    return backend


def model_classes(
    cfg: Any, dataset: SceneDataset, fallback: ClassList | None, registry: Registry | None = None
) -> ClassList:
    """The dataset's classes, or ``fallback`` (a checkpoint's) when the dataset has no class list.

    Raises:
        ConfigError: the dataset has no class list, there is no fallback and the config has a head that predicts
            classes (it would have none).
    """
    if dataset.class_names:
        return ClassList(tuple(dataset.class_names), int(dataset.ignore_index), f"dataset {cfg.dataset.name!r}")
    if fallback is not None:
        return fallback
    head = cfg.get("head")
    if head is not None and head_predicts(head, registry or get_registry()) == "classes":
        raise ConfigError(
            f"dataset {cfg.dataset.name!r} has no class list (class_names is empty), so head {head.name!r} has no "
            "classes to predict; train on a dataset with classes, or start from a trained model: eval, render and "
            "finetune checkpoint=<.pt> use the classes the checkpoint stores (one written before checkpoints stored "
            "them has none)"
        )
    return ClassList((), int(dataset.ignore_index), f"dataset {cfg.dataset.name!r}")


def build_components(cfg: Any, registry: Registry | None = None, *, classes: ClassList | None = None) -> Components:
    """Build the dataset, view selector, model and loss set of ``cfg``.

    Args:
        classes: the classes to build the head with when the dataset has no class list (a checkpoint's:
            ``checkpoint_classes``); a dataset with its own list always uses it.
    """
    registry = registry or get_registry()
    dataset = registry.build("dataset", cfg.dataset)
    selector = registry.build("view_selector", cfg.view_selector)
    label_space = model_classes(cfg, dataset, classes, registry)
    model = build_model(cfg, label_space.num_classes, registry)
    # Every checkpoint of this model stores its classes (save_checkpoint reads them here), so eval, render and finetune
    # can name them on a dataset that has none.
    model.classes = label_space
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
    return Components(dataset=dataset, view_selector=selector, model=model, loss=loss, classes=label_space)
