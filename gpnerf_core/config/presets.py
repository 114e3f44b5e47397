"""Config presets plugins ship (``gpnerf_config_searchpaths``): the folders Hydra searches after gpnerf-core's ``conf/``,
and the refusal of a plugin's preset that would shadow a built-in one (or another plugin's).

Hydra takes the first search path that has a config, so a plugin's ``experiment/table4_id5.yaml`` would silently lose
to the built-in one, or (were it searched first) replace it. Neither is allowed: presets add to the built-in ones, and
a file two places ship is refused in one line naming both, like a component name two plugins register.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path
from typing import Any, Iterable

from gpnerf_core.errors import ConfigError

PROVIDER = "gpnerf-plugin"
"""Hydra's provider name of a plugin's search path: ``gpnerf-plugin:<plugin name>``."""


def plugin_search_paths(registry: Any = None) -> list[tuple[str, str]]:
    """``(Hydra provider, search path)`` of every plugin's config folder, in registration order."""
    from gpnerf_core.registry.components import get_registry

    registry = registry or get_registry()
    return [(f"{PROVIDER}:{plugin}", path) for path, plugin in registry.config_searchpaths]


def config_files(path: str) -> set[str]:
    """The YAML files below a search path (``pkg://<package>.<folder>``, ``file://<folder>``), relative to it
    (``experiment/mine.yaml``); empty when it cannot be read (Hydra then reports the path itself)."""
    scheme, _, where = path.partition("://")
    try:
        root: Any = Path(where) if scheme == "file" else importlib.resources.files(where.replace("/", ".").strip("."))
    except (ImportError, TypeError, ValueError):
        return set()
    return set(_yaml_below(root, ""))


def _yaml_below(folder: Any, prefix: str) -> Iterable[str]:
    try:
        entries = list(folder.iterdir())
    except OSError:
        return
    for entry in entries:
        if entry.is_dir():
            yield from _yaml_below(entry, f"{prefix}{entry.name}/")
        elif entry.name.endswith(".yaml"):
            yield f"{prefix}{entry.name}"


def preset_clashes(registry: Any = None) -> list[str]:
    """One line per config file a plugin's search path shares with gpnerf-core's ``conf/`` or an earlier plugin's."""
    from gpnerf_core.config.folder import config_dir
    from gpnerf_core.registry.components import disable_name, get_registry
    from gpnerf_core.registry.plugins import DISABLE_PLUGINS_ENV, PluginInfo

    registry = registry or get_registry()
    if not registry.config_searchpaths:
        return []
    owners = {name: "gpnerf-core's built-in conf/" for name in config_files(f"file://{config_dir()}")}
    clashes = []
    for path, plugin in registry.config_searchpaths:
        here = f"plugin {plugin} ({path})"
        for name in sorted(config_files(path)):
            if name in owners:
                off = disable_name(registry.plugins.get(plugin, PluginInfo(plugin)))
                clashes.append(f"config preset {name} of {here} shadows the one of {owners[name]}; a plugin's presets "
                               f"add to the others and never replace them: rename it (or disable the plugin, "
                               f"{DISABLE_PLUGINS_ENV}={off})")
            else:
                owners[name] = here
    return clashes


def check_presets(registry: Any = None) -> None:
    """Refuse (``ConfigError``, one line) a plugin's config preset that shadows a built-in or another plugin's."""
    clashes = preset_clashes(registry)
    if clashes:
        more = f" (and {len(clashes) - 1} more: python -m gpnerf_core plugins lists them)" if len(clashes) > 1 else ""
        raise ConfigError(clashes[0] + more)
