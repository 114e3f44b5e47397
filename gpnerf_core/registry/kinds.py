"""The kinds of component a plugin can register: one record per kind, the only place a kind is declared.

A kind is a registry key, a Hydra config group of the same name, a registration hook (``hookspecs``), an interface its
components implement and the keyword arguments the core passes its factories besides the config fields. Adding a kind
is one ``ComponentKind`` here, its hook in ``hookspecs`` and its interface in ``gpnerf_core.interfaces``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gpnerf_core import interfaces as I  # noqa: N812 - the interfaces package
from gpnerf_core.data.dataset import SceneDataset
from gpnerf_core.interfaces.model import ModelFamily


@dataclass(frozen=True)
class ComponentKind:
    """One kind of component.

    Attributes:
        name: the registry key and the Hydra config group (``+head=unet``, ``dataset=replica``).
        hook: the registration hook (``gpnerf_register_<kind>s``) returning its ``ComponentSpec`` s.
        interface: the class every built component is an instance of.
        runtime_arguments: keyword arguments the core passes the factory besides the config fields.
        add_on: absent by default and selected with ``+`` (``+head=<name>``); otherwise always in the config.
        defines_model: its config section is part of the trained model (resuming or fine-tuning with other values is
            refused, ``eval`` restores the checkpoint's values).
        core_fields: fields every config of the kind has (its base config's) that the core reads itself and does not
            pass to the factory.
        core_options: fields a config of the kind may have that the core reads itself and does not pass to the
            factory (a model family's own learning rates, ``model.lr``, and family loss-term weights,
            ``model.loss_weights``).
        part: a part a model family builds (``ModelParts.build``): its Hydra group is mounted under ``model``
            (``model/<kind>=<name>``, keys ``model.<kind>.<option>``) and the family's config declares it
            (``declarations.part``); its section belongs to the model's, so it defines no section of its own.
    """

    name: str
    hook: str
    interface: type
    runtime_arguments: tuple[str, ...] = ()
    add_on: bool = False
    defines_model: bool = False
    core_fields: tuple[str, ...] = ()
    core_options: tuple[str, ...] = ()
    part: bool = False

    @property
    def group(self) -> str:
        """The Hydra config group of its options: ``model/<kind>`` for a part, else ``<kind>``."""
        return f"model/{self.name}" if self.part else self.name

    @property
    def config_key(self) -> str:
        """The dotted key of its section in a composed config: ``model.<kind>`` for a part, else ``<kind>``."""
        return f"model.{self.name}" if self.part else self.name

    @property
    def withheld(self) -> frozenset[str]:
        """The config fields the core keeps from the factory: ``name``, ``core_fields`` and ``core_options``."""
        return frozenset({"name", *self.core_fields, *self.core_options})


KINDS: dict[str, ComponentKind] = {
    kind.name: kind
    for kind in (
        ComponentKind("model", "gpnerf_register_models", ModelFamily, ("parts",), defines_model=True,
                      core_fields=("num_source_views", "init", "init_strict"), core_options=("lr", "loss_weights")),
        ComponentKind("feature_extractor", "gpnerf_register_feature_extractors", I.FeatureExtractor, part=True),
        ComponentKind("field_aggregator", "gpnerf_register_field_aggregators", I.FieldAggregator, ("in_dim",),
                      part=True),
        ComponentKind("ray_aggregator", "gpnerf_register_ray_aggregators", I.RayAggregator, ("in_dim", "num_blocks"),
                      part=True),
        ComponentKind("head", "gpnerf_register_heads", I.PerceptionHead, ("in_dim", "in_levels", "num_outputs"),
                      add_on=True, defines_model=True),
        ComponentKind("loss", "gpnerf_register_losses", I.LossSet, add_on=True, defines_model=True),
        ComponentKind("dataset", "gpnerf_register_datasets", SceneDataset),
        ComponentKind("view_selector", "gpnerf_register_view_selectors", I.ViewSelector),
        ComponentKind("depth_source", "gpnerf_register_depth_sources", I.DepthSource, add_on=True,
                      defines_model=True),
        ComponentKind("feature_provider", "gpnerf_register_feature_providers", I.FeatureProvider, add_on=True),
    )
}
"""Every component kind by name, in the order ``plugins`` lists them."""

PART_KINDS = tuple(kind.name for kind in KINDS.values() if kind.part)
"""The kinds a model family builds as its parts, mounted under ``model``."""
GROUPS = {kind.group: kind.name for kind in KINDS.values()}
"""Hydra config group -> kind (``model/feature_extractor`` -> ``feature_extractor``)."""


def section(config: Any, kind: str) -> Any:
    """The section of ``kind`` in a config (a composed ``DictConfig`` or plain dicts): ``config.model.<kind>`` for a
    part, ``config.<kind>`` otherwise; None where the config has none."""
    node = config
    for key in KINDS[kind].config_key.split("."):
        node = node.get(key) if node is not None and hasattr(node, "get") else None
    return node

OTHER_HOOKS = ("gpnerf_register_data_tools", "gpnerf_register_stress_cases", "gpnerf_config_searchpaths")
"""Hooks whose records are not Hydra config options."""
