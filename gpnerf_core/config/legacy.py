"""Configs written by earlier versions, brought to today's keys: one table, applied wherever a stored config is read
back (a checkpoint's config and overrides).

Keys move as the framework grows (``train.fuse_rendered`` became an option of the ``gnt`` model family when models
became families); a checkpoint keeps the keys it was written with. Reading it maps them, so it still evaluates, renders,
fine-tunes and resumes, and its config compares with today's.
"""

from __future__ import annotations

from typing import Any

import yaml

from gpnerf_core.config.overrides import override_key

MOVED_KEYS = {"train.fuse_rendered": "model.fuse_rendered"}
"""Old dotted key -> today's."""
DEFAULT_MODEL = "gnt"
"""The model family of a config written before ``model`` named one (there was only GNT's)."""


def upgrade_overrides(overrides: list[str]) -> list[str]:
    """Stored Hydra overrides with moved keys renamed (``train.fuse_rendered=false`` -> ``model.fuse_rendered=false``)."""
    upgraded = []
    for override in overrides:
        key = override_key(override)
        if key in MOVED_KEYS:
            prefix = override[: len(override) - len(override.lstrip("+~"))]
            override = f"{prefix}{MOVED_KEYS[key]}{override[len(prefix) + len(key):]}"
        upgraded.append(override)
    return upgraded


def upgrade_config_yaml(text: str) -> str:
    """A stored config (YAML) with moved keys moved and the model family named; unchanged when already current."""
    config = yaml.safe_load(text) or {}
    if not isinstance(config, dict):
        return text
    changed = False
    for old, new in MOVED_KEYS.items():
        value = _pop(config, old)
        if value is not _MISSING:
            _put(config, new, value)
            changed = True
    model = config.get("model")
    if isinstance(model, dict) and "name" not in model:
        config["model"] = {"name": DEFAULT_MODEL, **model}
        changed = True
    return yaml.safe_dump(config, sort_keys=False) if changed else text


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
