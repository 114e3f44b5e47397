"""Finds the plugin a kit call names and loads it next to the built-in plugins, as the pipeline would.

A target is an entry-point name (group ``gpnerf``), a distribution name, a plugin module or a module path. Entry
points are loaded explicitly, so the kit works with ``GPNERF_DISABLE_PLUGIN_AUTOLOAD=1``; a module works uninstalled.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from dataclasses import dataclass
from types import ModuleType
from typing import Any, Sequence, Union

from gpnerf_core.registry.plugins import (
    BUILTIN_PLUGINS,
    ENTRY_POINT_GROUP,
    PluginInfo,
    PluginProblem,
    import_problem,
    make_plugin_manager,
    normalize_distribution,
)
from gpnerf_core.registry.components import RegisteredComponent, Registry, collect
from gpnerf_core.registry.kinds import KINDS

Target = Union[str, ModuleType]


@dataclass(frozen=True)
class LoadedTarget:
    """The registry the kit checks against and what the target contributed to it.

    Attributes:
        registry: built-in plugins plus the target's plugins.
        plugins: the target's plugin names (entry-point or module names).
        components: the target's registered components, in kind order.
        problems: what the registry rejected of the target (a plugin that did not load, a component left out).
    """

    registry: Registry
    plugins: tuple[str, ...]
    components: tuple[RegisteredComponent, ...]
    problems: tuple[PluginProblem, ...]
    stress_cases: tuple[tuple[Any, str], ...] = ()
    """``(StressCase, plugin name)`` of the target's registered stress cases."""


def load_targets(targets: Target | Sequence[Target]) -> LoadedTarget:
    """Load ``targets`` next to the built-in plugins (entry points are not autoloaded) and collect the registry."""
    if isinstance(targets, (str, ModuleType)):
        targets = [targets]
    loaded = make_plugin_manager(autoload=False)
    names: list[str] = []
    early: list[PluginProblem] = []
    for target in targets:
        for info, plugin in _resolve(target):
            names.append(info.name)
            if isinstance(plugin, PluginProblem):
                early.append(plugin)
            elif loaded.manager.is_registered(plugin):
                continue  # a built-in plugin: already registered under its module name
            else:
                loaded.register(plugin, info)
    registry = collect(loaded)
    problems = tuple(early) + tuple(p for p in registry.problems if p.plugin.name in names and p not in early)
    components = tuple(
        entry for kind in KINDS for _, entry in sorted(registry.components[kind].items()) if entry.provider in names
    )
    cases = tuple(entry for entry in registry.stress_cases.values() if entry[1] in names)
    return LoadedTarget(registry, tuple(dict.fromkeys(names)), components, problems, cases)


def _resolve(target: Target) -> list[tuple[PluginInfo, Any]]:
    """``(info, plugin module or PluginProblem)`` for each plugin ``target`` stands for."""
    if isinstance(target, ModuleType):
        return [(_module_info(target), target)]
    if not isinstance(target, str) or not target:
        raise TypeError(f"a plugin target is an entry-point, distribution or module name, or a module; got {target!r}")
    entry_points = list(importlib.metadata.entry_points(group=ENTRY_POINT_GROUP))
    chosen = [ep for ep in entry_points if ep.name == target]
    if not chosen:
        chosen = [ep for ep in entry_points if ep.dist is not None and normalize_distribution(ep.dist.name) == normalize_distribution(target)]
    if chosen:
        return [_load_entry_point(ep) for ep in chosen]
    if target in BUILTIN_PLUGINS:
        return [(PluginInfo(target), importlib.import_module(target))]
    try:
        module = importlib.import_module(target)
    except ModuleNotFoundError as exc:
        if exc.name is not None and target.startswith(exc.name):
            installed = ", ".join(sorted(ep.name for ep in entry_points)) or "none"
            raise LookupError(
                f"no entry point in group {ENTRY_POINT_GROUP!r}, installed distribution or importable module named "
                f"{target!r} (installed gpnerf entry points: {installed})"
            ) from None
        raise
    return [(_module_info(module), module)]


def _load_entry_point(ep: importlib.metadata.EntryPoint) -> tuple[PluginInfo, Any]:
    info = PluginInfo(ep.name, ep.dist.name if ep.dist else "unknown", ep.dist.version if ep.dist else "unknown")
    try:
        return info, ep.load()
    except Exception as exc:
        return info, import_problem(info, exc)


def _module_info(module: ModuleType) -> PluginInfo:
    """The module's name, with the distribution that installed its top-level package when there is one."""
    top = module.__name__.split(".")[0]
    distributions = importlib.metadata.packages_distributions().get(top, [])
    if not distributions:
        return PluginInfo(module.__name__)
    name = distributions[0]
    try:
        return PluginInfo(module.__name__, name, importlib.metadata.version(name))
    except importlib.metadata.PackageNotFoundError:
        return PluginInfo(module.__name__, name)
