"""Component registry: collects specs from plugins, refuses duplicates, builds components from configs."""

from __future__ import annotations

import dataclasses
import functools
import importlib
import importlib.metadata
import os
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import pluggy

from gpnerf_core import hookspecs
from gpnerf_core.errors import ConfigError, PluginError

ENTRY_POINT_GROUP = "gpnerf"
DISABLE_AUTOLOAD_ENV = "GPNERF_DISABLE_PLUGIN_AUTOLOAD"
DISABLE_PLUGINS_ENV = "GPNERF_DISABLE_PLUGINS"

BUILTIN_PLUGINS: tuple[str, ...] = (
    "gpnerf_plugins.extractors.plugin",
    "gpnerf_plugins.transformers.plugin",
    "gpnerf_plugins.heads.plugin",
    "gpnerf_plugins.losses.plugin",
    "gpnerf_plugins.datasets.plugin",
    "gpnerf_plugins.view_selectors.plugin",
)

# kind -> hook name; the kind is also the Hydra config group.
KINDS: dict[str, str] = {
    "feature_extractor": "gpnerf_register_feature_extractors",
    "field_aggregator": "gpnerf_register_field_aggregators",
    "ray_aggregator": "gpnerf_register_ray_aggregators",
    "head": "gpnerf_register_heads",
    "loss": "gpnerf_register_losses",
    "dataset": "gpnerf_register_datasets",
    "view_selector": "gpnerf_register_view_selectors",
}


@dataclass(frozen=True)
class ComponentSpec:
    """A component a plugin offers.

    Attributes:
        name: registry key and Hydra option name (snake_case).
        factory: called as ``factory(**config_fields_without_name, **runtime_kwargs)``.
        config: a dataclass type whose fields are the factory's keyword arguments; its ``name`` field
            must default to ``name``. It becomes the Hydra option's schema.
        description: one line shown by ``python -m gpnerf_core plugins``.
    """

    name: str
    factory: Callable[..., Any]
    config: type
    description: str = ""


@dataclass(frozen=True)
class DataTool:
    """A subcommand of ``python -m gpnerf_core data``.

    Attributes:
        name: the subcommand (``check``, ``prepare-scannet``, ...).
        run: ``run(argv) -> exit code``; parses its own arguments.
        description: one line shown by ``python -m gpnerf_core data``.
    """

    name: str
    run: Callable[[list[str]], int]
    description: str = ""


@dataclass(frozen=True)
class RegisteredComponent:
    kind: str
    spec: ComponentSpec
    provider: str
    version: str


@dataclass
class Registry:
    """All registered components by kind and name, plus the plugins that failed to load."""

    components: dict[str, dict[str, RegisteredComponent]] = field(default_factory=lambda: {k: {} for k in KINDS})
    problems: list[tuple[str, str]] = field(default_factory=list)
    plugin_versions: dict[str, str] = field(default_factory=dict)
    data_tools: dict[str, tuple[DataTool, str]] = field(default_factory=dict)

    def names(self, kind: str) -> list[str]:
        return sorted(self.components[kind])

    def get(self, kind: str, name: str) -> RegisteredComponent:
        if kind not in self.components:
            raise ConfigError(f"unknown component kind {kind!r}; known kinds: {', '.join(KINDS)}")
        try:
            return self.components[kind][name]
        except KeyError:
            known = ", ".join(self.names(kind)) or "(none registered)"
            raise ConfigError(f"unknown {kind} {name!r}; known {kind} names: {known}") from None

    def build(self, kind: str, node: Mapping[str, Any], **runtime: Any) -> Any:
        """Build the component a config node names (``node['name']``) with its fields as kwargs."""
        if "name" not in node:
            raise ConfigError(f"config group {kind!r} has no 'name' key; known names: {', '.join(self.names(kind))}")
        entry = self.get(kind, str(node["name"]))
        kwargs = {k: _plain(v) for k, v in node.items() if k != "name"}
        expected = {f.name for f in dataclasses.fields(entry.spec.config)} - {"name"}
        unknown = set(kwargs) - expected
        if unknown:
            raise ConfigError(
                f"{kind}.{sorted(unknown)[0]} is not an option of {kind} {entry.spec.name!r}; "
                f"expected one of: {', '.join(sorted(expected))}"
            )
        return entry.spec.factory(**kwargs, **runtime)

    def add(self, kind: str, spec: ComponentSpec, provider: str, version: str) -> None:
        if not isinstance(spec, ComponentSpec):
            raise PluginError(f"plugin {provider!r} returned {type(spec).__name__} from {KINDS[kind]}, expected ComponentSpec")
        if not dataclasses.is_dataclass(spec.config):
            raise PluginError(f"plugin {provider!r}: config of {kind} {spec.name!r} is not a dataclass")
        default_name = {f.name: f.default for f in dataclasses.fields(spec.config)}.get("name")
        if default_name != spec.name:
            raise PluginError(
                f"plugin {provider!r}: {kind} {spec.name!r} has config {spec.config.__name__} whose 'name' "
                f"defaults to {default_name!r}; expected {spec.name!r}"
            )
        existing = self.components[kind].get(spec.name)
        if existing is not None:
            raise PluginError(
                f"duplicate {kind} {spec.name!r}: provided by both {existing.provider!r} and {provider!r}"
            )
        self.components[kind][spec.name] = RegisteredComponent(kind, spec, provider, version)


def _plain(value: Any) -> Any:
    """OmegaConf containers to plain Python, so components never see the config tree."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        return value
    if isinstance(value, (DictConfig, ListConfig)):
        return OmegaConf.to_container(value, resolve=True)
    return value


def _env_list(name: str) -> list[str]:
    return [item.strip() for item in os.environ.get(name, "").split(",") if item.strip()]


def make_plugin_manager(
    *, builtins: tuple[str, ...] = BUILTIN_PLUGINS, autoload: bool = True, blocked: tuple[str, ...] = ()
) -> tuple[pluggy.PluginManager, list[tuple[str, str]], dict[str, str]]:
    """Create the plugin manager with the built-in plugins and the ``gpnerf`` entry points.

    A plugin that fails to import is recorded in the returned problems (name, one-line reason) and the others
    still load. Returns ``(manager, problems, versions)`` where versions maps plugin name to its distribution
    version.
    """
    pm = pluggy.PluginManager(hookspecs.PROJECT_NAME)
    pm.add_hookspecs(hookspecs)
    problems: list[tuple[str, str]] = []
    versions: dict[str, str] = {}
    for name in (*blocked, *_env_list(DISABLE_PLUGINS_ENV)):
        pm.set_blocked(name)
    core_version = _distribution_version("gpnerf-core")
    for module_name in builtins:
        if pm.is_blocked(module_name):
            continue
        try:
            pm.register(importlib.import_module(module_name), name=module_name)
            versions[module_name] = core_version
        except Exception as exc:  # a broken plugin must not take the others down
            problems.append((module_name, f"{type(exc).__name__}: {exc}"))
    if autoload and not os.environ.get(DISABLE_AUTOLOAD_ENV):
        for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
            if pm.is_blocked(ep.name):
                continue
            if pm.get_plugin(ep.name) is not None or pm.is_registered(ep.name):
                problems.append((ep.name, f"entry point name {ep.name!r} is already registered by another plugin"))
                continue
            try:
                pm.register(ep.load(), name=ep.name)
                versions[ep.name] = ep.dist.version if ep.dist is not None else "unknown"
            except Exception as exc:
                problems.append((ep.name, f"{type(exc).__name__}: {exc}"))
    try:
        pm.check_pending()
    except pluggy.PluginValidationError as exc:
        raise PluginError(f"plugin {exc.plugin_name!r} implements an unknown hook: {exc}") from None
    return pm, problems, versions


def _distribution_version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def collect(pm: pluggy.PluginManager, problems: list[tuple[str, str]], versions: dict[str, str]) -> Registry:
    """Call every registration hook implementation and build the registry (duplicates raise)."""
    registry = Registry(problems=list(problems), plugin_versions=dict(versions))
    for kind, hook_name in KINDS.items():
        hook = getattr(pm.hook, hook_name)
        for impl in hook.get_hookimpls():  # registration order, for stable listings
            try:
                specs = impl.function()
            except Exception as exc:
                registry.problems.append((impl.plugin_name, f"{hook_name} raised {type(exc).__name__}: {exc}"))
                continue
            for spec in specs or ():
                registry.add(kind, spec, impl.plugin_name, versions.get(impl.plugin_name, "unknown"))
    for impl in pm.hook.gpnerf_register_data_tools.get_hookimpls():
        try:
            tools = impl.function()
        except Exception as exc:
            registry.problems.append((impl.plugin_name, f"gpnerf_register_data_tools raised {type(exc).__name__}: {exc}"))
            continue
        for tool in tools or ():
            if tool.name in registry.data_tools:
                raise PluginError(
                    f"duplicate data tool {tool.name!r}: provided by both "
                    f"{registry.data_tools[tool.name][1]!r} and {impl.plugin_name!r}"
                )
            registry.data_tools[tool.name] = (tool, impl.plugin_name)
    return registry


def register_config_options(registry: Registry) -> None:
    """Make every registered component an option of its Hydra config group (``+head=<name>``)."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    for kind, entries in registry.components.items():
        for name, entry in entries.items():
            cs.store(group=kind, name=name, node=entry.spec.config, provider=entry.provider)


@functools.cache
def get_registry() -> Registry:
    """The process-wide registry (built once; Hydra launcher workers rebuild it lazily)."""
    pm, problems, versions = make_plugin_manager()
    registry = collect(pm, problems, versions)
    register_config_options(registry)
    return registry
