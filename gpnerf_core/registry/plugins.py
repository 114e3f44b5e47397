"""Loading plugins: the built-in ones and the ``gpnerf`` entry points, each in isolation.

A plugin that cannot be imported, or implements a hook that does not exist or is not marked, is recorded as a
``PluginProblem`` and left out; every other plugin keeps working.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import re
import sys
import traceback
from dataclasses import dataclass, field

import pluggy

from gpnerf_core.registry import hookspecs
from gpnerf_core.registry.kinds import KINDS, OTHER_HOOKS

ENTRY_POINT_GROUP = "gpnerf"
DISABLE_AUTOLOAD_ENV = "GPNERF_DISABLE_PLUGIN_AUTOLOAD"
DISABLE_PLUGINS_ENV = "GPNERF_DISABLE_PLUGINS"
CORE_DISTRIBUTION = "gpnerf-core"

BUILTIN_PLUGINS: tuple[str, ...] = (
    "gpnerf_plugins.families.plugin",
    "gpnerf_plugins.extractors.plugin",
    "gpnerf_plugins.transformers.plugin",
    "gpnerf_plugins.heads.plugin",
    "gpnerf_plugins.losses.plugin",
    "gpnerf_plugins.datasets.plugin",
    "gpnerf_plugins.view_selectors.plugin",
    "gpnerf_plugins.depth_sources.plugin",
    "gpnerf_plugins.feature_providers.plugin",
    "gpnerf_plugins.stress.plugin",
)

@dataclass(frozen=True)
class PluginInfo:
    """Where a plugin comes from: its registered name, distribution and version."""

    name: str
    distribution: str = "unknown"
    version: str = "unknown"

    def __str__(self) -> str:
        return f"{self.name} ({self.distribution} {self.version})"


@dataclass(frozen=True)
class PluginProblem:
    """Something a plugin got wrong; its component (or the whole plugin) was left out.

    Attributes:
        plugin: where it happened; reason: one line.
        component: ``kind/name`` when one component was rejected, None when the whole plugin was left out.
    """

    plugin: PluginInfo
    reason: str
    component: str | None = None

    def __str__(self) -> str:
        what = f"{self.component} rejected" if self.component else "not loaded"
        return f"{self.plugin}: {what}: {self.reason}"


def one_line(exc: BaseException) -> str:
    """The first line of an exception's message (decoders and validators raise multi-line ones)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else "(no message)"


def _env_list(name: str) -> list[str]:
    return [item.strip() for item in os.environ.get(name, "").split(",") if item.strip()]


def normalize_distribution(name: str) -> str:
    """Distribution names compare as PEP 503 normalises them (``GpNeRF_Head.Fancy`` == ``gpnerf-head-fancy``)."""
    return re.sub(r"[-_.]+", "-", name).lower()


@dataclass
class LoadedPlugins:
    """A plugin manager with the plugins that registered, and what went wrong with the others."""

    manager: pluggy.PluginManager
    plugins: dict[str, PluginInfo] = field(default_factory=dict)
    problems: list[PluginProblem] = field(default_factory=list)
    disabled: list[str] = field(default_factory=list)

    def register(self, plugin: object, info: PluginInfo) -> bool:
        """Register one plugin object; a plugin whose hooks fail validation is recorded and left out."""
        try:
            self.manager.register(plugin, name=info.name)
        except (pluggy.PluginValidationError, ValueError) as exc:
            self.problems.append(PluginProblem(info, f"{type(exc).__name__}: {one_line(exc)}"))
            return False
        self.plugins[info.name] = info
        for name in unmarked_hooks(self.manager, plugin):
            self.problems.append(PluginProblem(
                info, f"{name} is not marked with @hookimpl (from gpnerf_core import hookimpl), so pluggy ignores it"))
        return True

    def check_hooks(self) -> None:
        """Leave out every plugin that implements a hook gpnerf-core does not define (a misspelled hook name)."""
        while True:
            try:
                self.manager.check_pending()
                return
            except pluggy.PluginValidationError as exc:
                name = self.manager.get_name(exc.plugin) or str(exc.plugin)
                self.manager.unregister(exc.plugin)
                info = self.plugins.pop(name, PluginInfo(name))
                known = ", ".join(sorted(kind.hook for kind in KINDS.values()) + list(OTHER_HOOKS))
                self.problems.append(
                    PluginProblem(info, f"implements a hook gpnerf-core does not define ({one_line(exc)}); "
                                        f"known hooks: {known}")
                )


def unmarked_hooks(manager: pluggy.PluginManager, plugin: object) -> list[str]:
    """Functions of ``plugin`` named like a gpnerf hook that carry no ``@hookimpl`` mark (silently skipped by pluggy)."""
    names = [name for name in dir(plugin) if name.startswith(f"{hookspecs.PROJECT_NAME}_")]
    return [name for name in names
            if callable(getattr(plugin, name, None)) and manager.parse_hookimpl_opts(plugin, name) is None]


def make_plugin_manager(
    *, builtins: tuple[str, ...] = BUILTIN_PLUGINS, autoload: bool = True, blocked: tuple[str, ...] = ()
) -> LoadedPlugins:
    """Load the built-in plugins and the ``gpnerf`` entry points, each in isolation.

    ``GPNERF_DISABLE_PLUGINS`` (and ``blocked``) name plugins to skip: built-in module names, entry-point names or
    distribution names. ``GPNERF_DISABLE_PLUGIN_AUTOLOAD`` skips every entry point.
    """
    pm = pluggy.PluginManager(hookspecs.PROJECT_NAME)
    pm.add_hookspecs(hookspecs)
    loaded = LoadedPlugins(pm)
    blocked_names = {*blocked, *_env_list(DISABLE_PLUGINS_ENV)}
    core_version = _distribution_version(CORE_DISTRIBUTION)
    for module_name in builtins:
        info = PluginInfo(module_name, CORE_DISTRIBUTION, core_version)
        if module_name in blocked_names:
            loaded.disabled.append(module_name)
            continue
        try:
            module = importlib.import_module(module_name)
        except Exception as exc:  # a broken plugin must not take the others down
            loaded.problems.append(import_problem(info, exc))
            continue
        loaded.register(module, info)
    if autoload and os.environ.get(DISABLE_AUTOLOAD_ENV):
        loaded.disabled.append(f"every entry point ({DISABLE_AUTOLOAD_ENV} is set)")
    elif autoload:
        enabled, disabled = enabled_entry_points(blocked)
        loaded.disabled.extend(str(info) for info in disabled)
        for ep in enabled:
            info = entry_point_info(ep)
            if ep.name in loaded.plugins or pm.has_plugin(ep.name):
                loaded.problems.append(PluginProblem(info, f"entry point name {ep.name!r} is taken by another plugin"))
                continue
            try:
                plugin = ep.load()
            except Exception as exc:
                loaded.problems.append(import_problem(info, exc))
                continue
            loaded.register(plugin, info)
    return loaded


def entry_point_info(ep: importlib.metadata.EntryPoint) -> PluginInfo:
    """The plugin an entry point names: its name, distribution and version."""
    if ep.dist is None:
        return PluginInfo(ep.name)
    return PluginInfo(ep.name, ep.dist.name, ep.dist.version)


def enabled_entry_points(
    blocked: tuple[str, ...] = (),
) -> tuple[list[importlib.metadata.EntryPoint], list[PluginInfo]]:
    """The ``gpnerf`` entry points to load and those ``GPNERF_DISABLE_PLUGINS`` (or ``blocked``) leaves out; none at
    all under ``GPNERF_DISABLE_PLUGIN_AUTOLOAD``."""
    if os.environ.get(DISABLE_AUTOLOAD_ENV):
        return [], []
    blocked_names = {*blocked, *_env_list(DISABLE_PLUGINS_ENV)}
    blocked_distributions = {normalize_distribution(name) for name in blocked_names}
    enabled, disabled = [], []
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        info = entry_point_info(ep)
        if ep.name in blocked_names or normalize_distribution(info.distribution) in blocked_distributions:
            disabled.append(info)
        else:
            enabled.append(ep)
    return enabled, disabled


def import_problem(info: PluginInfo, exc: Exception) -> PluginProblem:
    """The one-line problem of a plugin that failed to import; with ``GPNERF_DEBUG`` set, its traceback on stderr."""
    if os.environ.get("GPNERF_DEBUG"):
        traceback.print_exception(exc, file=sys.stderr)
    return PluginProblem(info, f"import failed: {type(exc).__name__}: {one_line(exc)}")


def _distribution_version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


