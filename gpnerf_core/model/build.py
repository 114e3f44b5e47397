"""Builds what a config names through the registry: the dataset, the view selector, the model family (which builds
its own parts through ``ConfiguredParts``) and the loss set, and checks that they fit together."""

from __future__ import annotations

import inspect
import typing
from dataclasses import dataclass
from typing import Any

from gpnerf_core.data.dataset import SceneDataset
from gpnerf_core.errors import ConfigError
from gpnerf_core.features.build import build_feature_provider
from gpnerf_core.features.cache import frame_features
from gpnerf_core.features.field import FeatureField, FeatureFieldOptions, quiet_rng
from gpnerf_core.interfaces import LossSet, PerceptionHead, ViewSelector
from gpnerf_core.interfaces.head import Predicts
from gpnerf_core.interfaces.model import ModelFamily, ModelParts
from gpnerf_core.model.classes import ClassList
from gpnerf_core.model.loss_fit import check_loss_fits, check_predictions_fit, declared_head_predicts
from gpnerf_core.registry.components import Registry, get_registry
from gpnerf_core.registry.guards import guard_outputs
from gpnerf_core.registry.kinds import KINDS, section


@dataclass
class Components:
    """What a config builds.

    Attributes:
        classes: the classes the model predicts (and evaluation scores, renders and names): the dataset's, or, for a
            dataset without a class list (a capture without labels), the checkpoint's the model was trained with.
        model_sections: the config sections that define this model (``model_sections``): written into its
            checkpoints, so resuming, fine-tuning and evaluating compare and restore only those.
        feature_field: the feature provider the model's feature field is distilled from (``+feature_provider``:
            the trainer's distillation term and evaluation's feature fidelity read it), or None.
    """

    dataset: SceneDataset
    view_selector: ViewSelector
    model: ModelFamily
    loss: LossSet | None
    classes: ClassList
    model_sections: tuple[str, ...] = ()
    feature_field: FeatureField | None = None


def head_predicts(head_cfg: Any, registry: Registry) -> Predicts:
    """What the head ``head_cfg`` names predicts (``PerceptionHead.predicts``)."""
    return Predicts(getattr(registry.get("head", str(head_cfg["name"])).spec.factory, "predicts", Predicts.CLASSES))


def head_outputs(head_cfg: Any, num_classes: int, registry: Registry) -> int:
    """``num_outputs`` of a head: the dataset's classes, or ``slots + 1`` for an instance head."""
    if head_predicts(head_cfg, registry) is not Predicts.INSTANCES:
        return num_classes
    slots = head_cfg.get("slots")
    if not isinstance(slots, int) or isinstance(slots, bool):
        raise ConfigError(
            f"head {head_cfg['name']!r} predicts instances, so its config needs head.slots, an integer; got {slots!r}"
        )
    return slots + 1  # the head itself checks the value


class ConfiguredParts(ModelParts):
    """``ModelParts`` of a composed config: a model family builds the components the config selects through it.

    A head's or feature extractor's output is checked where it is made (``registry.guards``): the wrong shape or a
    NaN stops the run naming that component and its plugin."""

    def __init__(self, cfg: Any, num_classes: int, registry: Registry, dataset: SceneDataset | None = None) -> None:
        self._cfg = cfg
        self._num_classes = int(num_classes)
        self._registry = registry
        self._dataset = dataset
        self.built_feature_field: FeatureField | None = None
        """The feature field the family took (``feature_field``), or None."""
        self.built: list[Any] = []
        """The components built through it, in order."""
        self.built_kinds: set[str] = set()
        """The kinds of those components."""

    @property
    def num_classes(self) -> int:
        return self._num_classes

    def __repr__(self) -> str:
        chosen = ", ".join(f"{kind}={self.name(kind)}" for kind in KINDS if kind != "model" and self.configured(kind))
        return f"parts({chosen}; {self._num_classes} classes)"

    def configured(self, kind: str) -> bool:
        if kind not in KINDS:
            raise ConfigError(f"unknown component kind {kind!r}; known kinds: {', '.join(KINDS)}")
        return section(self._cfg, kind) is not None

    def name(self, kind: str) -> str | None:
        """The configured component name of ``kind`` (None when the config selects none)."""
        return str(section(self._cfg, kind).name) if self.configured(kind) else None

    def build(self, kind: str, **runtime: Any) -> Any:
        if not self.configured(kind):
            raise ConfigError(f"model {self._cfg.model.name!r} needs a {kind}; the config selects none: choose one "
                              f"with {KINDS[kind].group}=<name> (known: {', '.join(self._registry.names(kind))})")
        component = self._registry.build(kind, section(self._cfg, kind), **runtime)
        model = self._registry.components["model"].get(str(self._cfg.model.name))
        guard_outputs(kind, component, self._registry.get(kind, self.name(kind)).where,
                      upstream=model.where if model is not None else None)
        self.built.append(component)
        self.built_kinds.add(kind)
        return component

    def head(self, *, in_dim: int, in_levels: int) -> PerceptionHead | None:
        if not self.configured("head"):
            return None
        outputs = head_outputs(self._cfg.head, self._num_classes, self._registry)
        return self.build("head", in_dim=in_dim, in_levels=in_levels, num_outputs=outputs)

    def feature_field(self) -> FeatureField | None:
        """The configured ``+feature_provider`` built once, with the ``features`` options and the dataset's frames
        read through the provider cache (``frame_features``), or None without one."""
        provider_cfg = self._cfg.get("feature_provider")
        if provider_cfg is None:
            return None
        if self.built_feature_field is None:
            with quiet_rng():  # a provider's layers draw nothing the model's own would have drawn
                provider = build_feature_provider(self._cfg, self._registry)
            self.built_feature_field = FeatureField(
                provider, FeatureFieldOptions.from_config(self._cfg.get("features")),
                name=str(provider_cfg.get("name")), dataset=self._dataset, reader=frame_features)
            self.built_kinds.add("feature_provider")
        return self.built_feature_field


def family_class(registry: Registry, name: str) -> type | None:
    """The class the model family ``name`` builds (its factory, or its factory's return annotation), or None."""
    entry = registry.components.get("model", {}).get(name)
    if entry is None:
        return None
    factory = entry.spec.factory
    if inspect.isclass(factory):
        return factory
    try:
        returned = typing.get_type_hints(factory).get("return")
    except Exception:  # an annotation that does not resolve: unknown
        return None
    return returned if inspect.isclass(returned) else None


def feature_field_families(registry: Registry) -> list[str]:
    """The registered model families that render a feature field (``Capabilities.feature_field``), by name."""
    names = []
    for name in registry.names("model"):
        cls = family_class(registry, name)
        if cls is not None and getattr(getattr(cls, "capabilities", None), "feature_field", False):
            names.append(name)
    return names


def check_feature_field(cfg: Any, registry: Registry) -> None:
    """A ConfigError in one line when ``+feature_provider`` is configured for a family that renders no feature field,
    naming the family and those that do."""
    provider = cfg.get("feature_provider")
    if provider is None:
        return
    family = str(cfg.model.name)
    cls = family_class(registry, family)
    if cls is not None and getattr(cls.capabilities, "feature_field", False):
        return
    able = ", ".join(feature_field_families(registry)) or "none registered"
    raise ConfigError(f"+feature_provider={provider.get('name')}: model={family} renders no feature field to distil "
                      f"it into; expected one of the families that do: {able} (or drop +feature_provider)")


MODEL_ADD_ONS = ("head", "depth_source")
"""Add-on kinds a model family builds through its parts: one the config selects and the family never builds would
be silently ignored, so it is refused."""


def build_model(cfg: Any, num_classes: int, registry: Registry | None = None) -> ModelFamily:
    """The model family ``cfg.model`` names, built with its options and the config's parts.

    Raises:
        ConfigError: the config selects a head or depth source the family does not use.
    """
    return built_model(cfg, num_classes, registry)[0]


def built_model(cfg: Any, num_classes: int, registry: Registry | None = None) -> tuple[ModelFamily, tuple[str, ...]]:
    """``build_model``, and the config sections that define the model built (``model_sections``)."""
    return _built(cfg, num_classes, registry or get_registry())[:2]


def _built(cfg: Any, num_classes: int, registry: Registry, dataset: SceneDataset | None = None
           ) -> tuple[ModelFamily, tuple[str, ...], FeatureField | None]:
    """``built_model``, and the feature field the family took (None without ``+feature_provider``)."""
    check_feature_field(cfg, registry)
    parts = ConfiguredParts(cfg, num_classes, registry, dataset)
    model = registry.build("model", cfg.model, parts=parts)
    if cfg.get("feature_provider") is not None and parts.built_feature_field is None:
        raise ConfigError(f"+feature_provider={cfg.feature_provider.get('name')}: model={cfg.model.name} declares a "
                          "feature field (Capabilities.feature_field) but as configured built none; it would be "
                          "ignored")
    for kind in MODEL_ADD_ONS:
        if parts.configured(kind) and kind not in parts.built_kinds:
            raise ConfigError(f"+{kind}={parts.name(kind)}: model {cfg.model.name!r} as configured uses no {kind} "
                              f"(it would be ignored); drop +{kind}=..., or choose a model that reads one "
                              f"(docs/configuration.md)")
    return model, model_sections(parts.built_kinds), parts.built_feature_field


def model_sections(built_kinds: set[str] | frozenset[str]) -> tuple[str, ...]:
    """The config sections that define a model whose family built the components ``built_kinds``: ``model`` (with the
    parts mounted under it), ``loss``, and each add-on the family built that defines a model
    (``ComponentKind.defines_model``: ``head``, ``depth_source``), in ``KINDS`` order. An add-on the family never
    built is not the model's: changing its options is no model change. A family that took a feature provider
    (``parts.feature_field``) adds ``feature_provider`` and ``features``: the field it learnt is that provider's, at those
    channels."""
    sections = tuple(kind.name for kind in KINDS.values() if kind.defines_model
                     and (kind.name in ("model", "loss") or kind.name in built_kinds))
    return (*sections, "feature_provider", "features") if "feature_provider" in built_kinds else sections


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
    if head is not None and head_predicts(head, registry or get_registry()) is Predicts.CLASSES:
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
        classes: the classes to build the model with when the dataset has no class list (a checkpoint's:
            ``checkpoint_classes``); a dataset with its own list always uses it.
    """
    registry = registry or get_registry()
    dataset = registry.build("dataset", cfg.dataset)
    selector = registry.build("view_selector", cfg.view_selector)
    label_space = model_classes(cfg, dataset, classes, registry)
    model, sections, feature_field = _built(cfg, label_space.num_classes, registry, dataset)
    loss = None
    if cfg.get("loss") is not None:
        check_predictions_fit(cfg, model, declared_head_predicts(cfg, registry))  # before the loss's own checks
        loss = registry.build("loss", cfg.loss)
        check_loss_fits(cfg, model, loss, num_classes=label_space.num_classes, registry=registry)
    return Components(dataset=dataset, view_selector=selector, model=model, loss=loss, classes=label_space,
                      model_sections=sections, feature_field=feature_field)
