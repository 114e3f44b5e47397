"""Configs written by earlier versions, brought to today's keys: one table, applied wherever a stored config is read
back (a checkpoint's config, overrides and model sections; a run folder's config for ``report``).

Keys move as the framework grows (``train.fuse_rendered`` became an option of GP-NeRF's model family when models
became families; the parts a family builds moved under ``model``, and ``train.lr.<group>`` became ``model.lr.<group>``,
when families came to own their config subtree); a checkpoint keeps the keys it was written with. Reading it maps them, so it still evaluates, renders, fine-tunes and
resumes, and its config compares with today's.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Iterable

import yaml

from gpnerf_core.config.overrides import override_key
from gpnerf_core.registry.kinds import KINDS, PART_KINDS

MOVED_KEYS = {"train.fuse_rendered": "model.fuse_rendered"}
"""Old dotted key -> today's."""
OLD_RATES = "train.lr."
"""Where the learning rates were, beside a family's own ``model.lr``: now ``model.lr.<group>`` only."""
DEFAULT_MODEL = "gnt"
"""The model family of a config written before ``model`` named one (there was only GNT's)."""


def _family_config(model: str | None) -> type | None:
    from gpnerf_core.registry.components import get_registry

    entry = get_registry().components["model"].get(str(model or DEFAULT_MODEL))
    return None if entry is None else entry.spec.config


def family_parts(model: str | None) -> tuple[str, ...]:
    """The part kinds the model family ``model`` declares (``declarations.part``); every part kind for a family this
    installation does not register (its sections are kept, so nothing it may have built is lost)."""
    from gpnerf_core.registry.declarations import declared_parts

    config = _family_config(model)
    return PART_KINDS if config is None else tuple(declared_parts(config))


def family_rate_groups(model: str | None) -> tuple[str, ...] | None:
    """The learning-rate groups the model family ``model`` declares (its config's ``lr`` section); None for a family
    this installation does not register (every old rate is kept)."""
    config = _family_config(model)
    if config is None:
        return None
    lr = getattr(config(), "lr", None)
    return tuple(dataclasses.asdict(lr) if dataclasses.is_dataclass(lr) else dict(lr or {}))


def upgrade_overrides(overrides: list[str], model: str | None = None) -> list[str]:
    """Stored Hydra overrides with moved keys renamed (``train.fuse_rendered=false`` -> ``model.fuse_rendered=false``;
    a part's ``feature_extractor=<name>`` -> ``model/feature_extractor=<name>`` and ``feature_extractor.widths=[..]``
    -> ``model.feature_extractor.widths=[..]``; ``train.lr.head=..`` -> ``model.lr.head=..``). A part or a rate the
    run's model family ``model`` (the stored config's) does not have is dropped: it never reached the model."""
    upgraded = []
    parts: tuple[str, ...] | None = None
    groups: tuple[str, ...] | None = ()
    for override in overrides:
        key = override_key(override)
        prefix = override[: len(override) - len(override.lstrip("+~"))]
        rest = override[len(prefix) + len(key):]
        kind = key.split(".")[0]
        if key in MOVED_KEYS:
            override = f"{prefix}{MOVED_KEYS[key]}{rest}"
        elif key.startswith(OLD_RATES):
            groups = family_rate_groups(model) if groups == () else groups
            if groups is not None and key[len(OLD_RATES):] not in groups:
                continue
            override = f"{prefix}model.lr.{key[len(OLD_RATES):]}{rest}"
        elif kind in PART_KINDS:
            parts = family_parts(model) if parts is None else parts
            if kind not in parts:
                continue
            moved = f"{KINDS[kind].group}{key[len(kind):]}" if key == kind else f"model.{key}"
            override = f"{prefix}{moved}{rest}"
        upgraded.append(override)
    return upgraded


def upgrade_sections(sections: Iterable[str]) -> tuple[str, ...]:
    """A checkpoint's recorded model sections (``model_sections``) without the parts, now inside ``model``'s."""
    return tuple(s for s in sections if s not in PART_KINDS)


def upgrade_config(config: dict[str, Any]) -> bool:
    """Bring a stored config (plain dicts) to today's keys in place; True when anything changed."""
    changed = False
    for old, new in MOVED_KEYS.items():
        value = _pop(config, old)
        if value is not _MISSING:
            _put(config, new, value)
            changed = True
    model = config.get("model")
    if isinstance(model, dict) and "name" not in model:
        config["model"] = model = {"name": DEFAULT_MODEL, **model}
        changed = True
    if isinstance(model, dict) and any(kind in config for kind in PART_KINDS):
        parts = family_parts(model.get("name"))
        for kind in PART_KINDS:
            value = config.pop(kind, _MISSING)
            if value is not _MISSING and kind in parts:
                model[kind] = value
        changed = True
    rates = _pop(config, OLD_RATES.rstrip("."))
    if isinstance(model, dict) and isinstance(rates, dict):
        groups = family_rate_groups(model.get("name"))
        own = model.get("lr") if isinstance(model.get("lr"), dict) else {}
        kept = {g: v for g, v in rates.items() if groups is None or g in groups}
        model["lr"] = {**kept, **own}  # the family's own rate won over train.lr's, as it did then
        changed = True
    return changed


def upgrade_config_yaml(text: str) -> str:
    """A stored config (YAML) with moved keys moved and the model family named; unchanged when already current."""
    config = yaml.safe_load(text) or {}
    if not isinstance(config, dict):
        return text
    return yaml.safe_dump(config, sort_keys=False) if upgrade_config(config) else text


_MISSING = object()


def _pop(config: dict[str, Any], dotted: str) -> Any:
    *parents, leaf = dotted.split(".")
    node: Any = config
    for part in parents:
        node = node.get(part) if isinstance(node, dict) else None
    return node.pop(leaf, _MISSING) if isinstance(node, dict) else _MISSING


def _put(config: dict[str, Any], dotted: str, value: Any) -> None:
    *parents, leaf = dotted.split(".")
    node = config
    for part in parents:
        node = node.setdefault(part, {})
    node[leaf] = value
