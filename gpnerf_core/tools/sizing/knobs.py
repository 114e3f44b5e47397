"""The knobs ``size`` turns down: the size knobs the configured model's family and parts declare on their config fields
(``gpnerf_core.size_knob``: a label and the smaller values to try), each as its dotted config key.

A knob's key is where its field sits in the composed config: ``model.<field>`` for the family's own (and the fields
every family has: ``model.num_source_views``, a ray-marching family's samples), ``model.<kind>.<field>`` for a part
it builds. The values come from the declaration, so they stay valid for the component that declares them; ``size``
reads no option by its name.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from omegaconf import OmegaConf


@dataclass(frozen=True)
class Knob:
    """A config key that costs time and memory, and how to shrink it.

    Attributes:
        key: dotted config key (``model.coarse_samples``).
        label: short name for tables.
        levels: ``reference value -> smaller values to try``, largest first.
        needs: an add-on kind without which the knob is not sized (``head``).
    """

    key: str
    label: str
    levels: Callable[[int], list[int]]
    needs: str | None = None


SOURCE_VIEWS = "model.num_source_views"
"""The knob the scene's coverage floors (``knob_levels``'s ``min_source_views``): every family has it."""


def component_knobs(config: type, prefix: str, registry: Any, node: Any = None) -> list[Knob]:
    """The knobs a component's config dataclass declares, keyed under ``prefix``; for a model family also those of the
    parts it declares (``node``: the composed model section, whose part names choose the parts' configs; None: each
    part's default), in the family's field order."""
    from gpnerf_core.registry.declarations import declared_knobs, declared_parts

    parts = declared_parts(config)
    declared = declared_knobs(config)
    found: list[Knob] = []
    for name in (f for f in getattr(config, "__dataclass_fields__", {}) if f in declared or f in parts):
        if name in declared:
            knob = declared[name]
            found.append(Knob(f"{prefix}{name}", knob.label, knob.levels, knob.needs))
            continue
        section = node.get(name) if node is not None else None
        chosen = section.get("name") if section is not None else parts[name]
        entry = registry.components[name].get(str(chosen)) if chosen is not None else None
        if entry is not None:
            found += component_knobs(entry.spec.config, f"{prefix}{name}.", registry)
    return found


def configured_knobs(cfg: Any, registry: Any = None, *, per_scene: bool = False) -> list[Knob]:
    """The knobs of the model ``cfg`` configures: its family's and those of the parts it builds (``per_scene``: a
    per-scene family reads no source views, so ``model.num_source_views`` is not one of them)."""
    from gpnerf_core.registry.components import get_registry

    registry = registry or get_registry()
    entry = registry.components["model"].get(str(cfg.model.name))
    knobs = [] if entry is None else component_knobs(entry.spec.config, "model.", registry, cfg.model)
    return [k for k in knobs if not (per_scene and k.key == SOURCE_VIEWS)]


def known_knobs(registry: Any = None) -> list[Knob]:
    """Every knob a registered family or part declares (``size.knobs`` names them), each key once."""
    from gpnerf_core.registry.components import get_registry
    from gpnerf_core.registry.kinds import PART_KINDS

    registry = registry or get_registry()
    found: dict[str, Knob] = {}
    for kind in ("model", *PART_KINDS):
        prefix = "model." if kind == "model" else f"model.{kind}."
        for name in registry.names(kind):
            for knob in component_knobs(registry.components[kind][name].spec.config, prefix, registry):
                found.setdefault(knob.key, knob)
    return list(found.values())


def knob_levels(
    cfg: Any, min_source_views: int, *, per_scene: bool = False
) -> tuple[dict[str, tuple[int, list[int]]], list[str]]:
    """Each of the configured model's knobs with its reference value and smaller levels, and notes on the knobs left
    out (another component's knob, one whose add-on is not configured, one with no smaller value).

    Args:
        cfg: the reference config.
        min_source_views: no fewer source views are tried (the scene's coverage floor).
        per_scene: the model is per-scene (no source views to size).
    """
    knobs = configured_knobs(cfg, per_scene=per_scene)
    own = {knob.key for knob in knobs} | ({SOURCE_VIEWS} if per_scene else set())
    notes = [f"{knob.key}: {_why_absent(cfg, knob.key)}; not sized" for knob in known_knobs() if knob.key not in own]
    levels: dict[str, tuple[int, list[int]]] = {}
    for knob in knobs:
        value = OmegaConf.select(cfg, knob.key, default=None)
        if value is None:
            notes.append(f"{knob.key}: not set in the configured model; not sized")
            continue
        if knob.needs is not None and cfg.get(knob.needs) is None:
            notes.append(f"{knob.key}: no {knob.needs} configured (+{knob.needs}=<name>), the only reader of what it "
                         "sizes; not sized")
            continue
        smaller = knob.levels(int(value))
        if knob.key == SOURCE_VIEWS:
            smaller = [v for v in smaller if v >= min_source_views]
            if not smaller:
                notes.append(f"{knob.key}: the scene needs all {value} (coverage floor {min_source_views})")
                continue
        if smaller:
            levels[knob.key] = (int(value), smaller)
    return levels, notes


def _why_absent(cfg: Any, key: str) -> str:
    """Why a known knob is not one of the configured model's: it builds no such part, or has no such option."""
    parts = key.split(".")
    if len(parts) == 3 and parts[1] not in cfg.model:
        return f"model {cfg.model.name!r} builds no {parts[1]}"
    return f"not an option of the configured {'.'.join(parts[:-1])} ({_name(cfg, parts)})"


def _name(cfg: Any, parts: list[str]) -> str:
    node = OmegaConf.select(cfg, ".".join(parts[:-1]), default=None)
    return f"{node.name!r}" if node is not None and "name" in node else "?"


def label_of(key: str) -> str:
    """The label a knob is declared with (the key itself for an unknown one)."""
    return next((k.label for k in known_knobs() if k.key == key), key)
