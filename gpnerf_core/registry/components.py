"""Component registry: collects specs from the loaded plugins, builds components from configs.

A plugin that returns a bad spec, registers a name another plugin already has, or offers a factory the core cannot
call is recorded as a ``PluginProblem`` and left out; every other plugin keeps working. A name two plugins register is
never resolved silently: choosing it is refused in one line naming both providers and how to keep one
(``GPNERF_DISABLE_PLUGINS``), until all but one are disabled. ``python -m gpnerf_core plugins`` lists the
problems (and exits 1 when there are any).
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import os
import re
import typing
from dataclasses import dataclass, field
from typing import Any, Iterator, Mapping

from gpnerf_core.errors import ConfigError, GpnerfError, PluginError
from gpnerf_core.interfaces import StressCase
from gpnerf_core.interfaces.model import capability_problems
from gpnerf_core.registry.declarations import declared_parts
from gpnerf_core.registry.kinds import KINDS, PART_KINDS
from gpnerf_core.registry.plugins import (
    CORE_DISTRIBUTION, DISABLE_PLUGINS_ENV, LoadedPlugins, PluginInfo, PluginProblem, make_plugin_manager, one_line,
)
from gpnerf_core.registry.specs import ComponentSpec, DataTool

NAME_PATTERN = re.compile(r"^[a-z][a-z0-9_]*$")
"""Component names: snake_case, starting with a letter (they are Hydra option names)."""


@dataclass(frozen=True)
class RegisteredComponent:
    """A registered component: its kind, spec, and the plugin (entry-point or module name) and distribution behind it."""

    kind: str
    spec: ComponentSpec
    provider: str
    version: str
    distribution: str = "unknown"

    @property
    def where(self) -> str:
        """``head 'unet' (plugin gpnerf_plugins.heads.plugin, gpnerf-core 0.1.0)``: for errors about it."""
        return f"{self.kind} {self.spec.name!r} (plugin {self.provider}, {self.distribution} {self.version})"


def disable_name(plugin: PluginInfo) -> str:
    """What ``GPNERF_DISABLE_PLUGINS`` takes to leave ``plugin`` out: a built-in's module name, else its distribution."""
    if plugin.distribution in (CORE_DISTRIBUTION, "unknown"):
        return plugin.name
    return plugin.distribution


def clash_message(what: str, providers: list[PluginInfo]) -> str:
    """One line: ``what`` (``head 'unet'``) is offered by each of ``providers``, and how to keep one of them."""
    if len(set(providers)) == 1:
        return (f"{what} is registered {len(providers)} times by {providers[0]}, and gpnerf-core does not pick one; "
                "the plugin must register each name once")
    offered = " and ".join(str(p) for p in providers)
    keep = "; ".join(
        f"to use {p.name}'s: {DISABLE_PLUGINS_ENV}={','.join(disable_name(o) for o in providers if o is not p)}"
        for p in providers
    )
    return (f"{what} is offered by {len(providers)} plugins, {offered}, and gpnerf-core does not pick one; "
            f"disable all but one ({keep})")


@dataclass
class Registry:
    """All registered components by kind and name, the plugins behind them and the problems found."""

    components: dict[str, dict[str, RegisteredComponent]] = field(default_factory=lambda: {k: {} for k in KINDS})
    problems: list[PluginProblem] = field(default_factory=list)
    plugins: dict[str, PluginInfo] = field(default_factory=dict)
    disabled: list[str] = field(default_factory=list)
    data_tools: dict[str, tuple[DataTool, str]] = field(default_factory=dict)
    stress_cases: dict[str, tuple[Any, str]] = field(default_factory=dict)
    """``name -> (StressCase, plugin name)``."""
    clashes: dict[str, list[PluginInfo]] = field(default_factory=dict)
    """``kind/name -> the plugins that each register it`` (first registered first); choosing one is refused."""
    config_searchpaths: list[tuple[str, str]] = field(default_factory=list)
    """``(Hydra search path, plugin name)`` of the config folders plugins ship (``gpnerf_config_searchpaths``), in
    registration order."""

    def names(self, kind: str) -> list[str]:
        return sorted(self.components[kind])

    def get(self, kind: str, name: str) -> RegisteredComponent:
        """The component ``name`` of ``kind``; an unknown name lists the known ones and what failed to load."""
        if kind not in self.components:
            raise ConfigError(f"unknown component kind {kind!r}; known kinds: {', '.join(KINDS)}")
        clash = self.clashes.get(f"{kind}/{name}")
        if clash is not None:
            raise PluginError(clash_message(f"{kind} {name!r}", clash))
        if name in self.components[kind]:
            return self.components[kind][name]
        rejected = [p for p in self.problems if p.component == f"{kind}/{name}"]
        if rejected:
            raise PluginError(f"{kind} {name!r} was rejected: {rejected[0]}")
        known = ", ".join(self.names(kind)) or "(none registered)"
        message = f"unknown {kind} {name!r}; known {kind} names: {known}"
        failed = [p for p in self.problems if p.component is None]
        if failed:
            message += "; plugins that failed to load: " + "; ".join(str(p) for p in failed)
        if self.disabled:
            message += (f"; disabled plugins (GPNERF_DISABLE_PLUGINS / GPNERF_DISABLE_PLUGIN_AUTOLOAD), which may "
                        f"provide it: {', '.join(self.disabled)}")
        raise ConfigError(message)

    def build(self, kind: str, node: Mapping[str, Any], **runtime: Any) -> Any:
        """Build the component a config node names (``node['name']``) with its fields as kwargs.

        Fields the node leaves out take their config dataclass defaults.

        A plugin's factory that raises anything but a gpnerf-core error, or returns something that does not
        implement the kind's interface, is reported in one line naming the component and its plugin.
        """
        if "name" not in node:
            raise ConfigError(f"config group {kind!r} has no 'name' key; known names: {', '.join(self.names(kind))}")
        entry = self.get(kind, str(node["name"]))
        withheld = withheld_fields(kind, entry.spec.config)
        given = {k: _plain(v) for k, v in node.items() if k not in withheld}
        expected = {f.name for f in dataclasses.fields(entry.spec.config)} - withheld
        unknown = set(given) - expected
        if unknown:
            raise ConfigError(
                f"{KINDS[kind].config_key}.{sorted(unknown)[0]} is not an option of {kind} {entry.spec.name!r}; "
                f"expected one of: {', '.join(sorted(expected))}"
            )
        defaults = entry.spec.config()
        kwargs = {name: given.get(name, getattr(defaults, name)) for name in sorted(expected)}
        where = entry.where
        try:
            component = entry.spec.factory(**kwargs, **runtime)
        except GpnerfError:
            raise
        except Exception as exc:
            if os.environ.get("GPNERF_DEBUG"):
                raise
            raise PluginError(f"{where} failed to build: {type(exc).__name__}: {one_line(exc)}") from None
        interface = KINDS[kind].interface
        if not isinstance(component, interface):
            raise PluginError(f"{where} built a {type(component).__name__}, which does not implement {interface.__name__}")
        if kind == "model":  # a factory whose class the registry could not see at registration
            problems = capability_problems(type(component))
            if problems:
                raise PluginError(f"{where} built a model whose capabilities do not hold: {problems[0]}")
        return component

    def add(self, kind: str, spec: Any, plugin: PluginInfo) -> None:
        """Register ``spec`` from ``plugin``, or record why it was rejected (the registry is left unchanged)."""
        try:
            self._check(kind, spec, plugin)
        except PluginError as exc:
            name = getattr(spec, "name", None)
            self.problems.append(PluginProblem(plugin, str(exc), f"{kind}/{name}" if isinstance(name, str) else kind))
            existing = self.components[kind].get(name) if isinstance(name, str) else None
            if existing is not None:
                self.clashes.setdefault(f"{kind}/{name}", [self.provider_of(existing)]).append(plugin)
            return
        self.components[kind][spec.name] = RegisteredComponent(
            kind, spec, plugin.name, plugin.version, plugin.distribution
        )

    def record_clash(self, kind: str, name: str, first: tuple[Any, str] | None, plugin: PluginInfo) -> list[PluginInfo]:
        """Record that ``plugin`` registers ``kind/name`` too (a data tool or stress case, whose registered ``first``,
        ``(record, plugin name)``, was just taken out, so neither runs); returns every plugin that registers it."""
        clash = self.clashes.setdefault(f"{kind}/{name}", [])
        if first is not None:
            clash.append(self.plugins.get(first[1], PluginInfo(first[1])))
        clash.append(plugin)
        return clash

    def provider_of(self, entry: RegisteredComponent) -> PluginInfo:
        """The plugin that registered ``entry``."""
        return self.plugins.get(entry.provider, PluginInfo(entry.provider, entry.distribution, entry.version))

    def _check(self, kind: str, spec: Any, plugin: PluginInfo) -> None:
        if not isinstance(spec, ComponentSpec):
            raise PluginError(f"{KINDS[kind].hook} returned {type(spec).__name__}, expected ComponentSpec")
        if not isinstance(spec.name, str) or not NAME_PATTERN.match(spec.name):
            raise PluginError(f"name {spec.name!r} is not snake_case (lower-case letters, digits, underscores)")
        existing = self.components[kind].get(spec.name)
        if existing is not None:
            raise PluginError(
                f"the name is taken by {existing.provider!r} ({existing.distribution} {existing.version}); "
                f"{kind}={spec.name} is refused until all but one of them are disabled "
                f"({DISABLE_PLUGINS_ENV}={disable_name(plugin)} keeps {existing.provider}'s)"
            )
        if not isinstance(spec.display_name, str) and not callable(spec.display_name):
            raise PluginError(f"display_name {spec.display_name!r} is neither a name nor a function of a run's config")
        if not dataclasses.is_dataclass(spec.config) or not isinstance(spec.config, type):
            raise PluginError(f"config {spec.config!r} is not a dataclass type")
        fields = {f.name: f for f in dataclasses.fields(spec.config)}
        default_name = fields["name"].default if "name" in fields else None
        if default_name != spec.name:
            raise PluginError(f"config {spec.config.__name__}.name defaults to {default_name!r}; expected {spec.name!r}")
        parts = declared_parts(spec.config)
        strange = [name for name in parts if kind != "model" or name not in PART_KINDS]
        if strange:
            raise PluginError(f"config {spec.config.__name__}.{strange[0]} is declared a part (part(...)); only a model "
                              f"family's config declares parts, each named after its kind: {', '.join(PART_KINDS)}")
        lacking = [name for name in KINDS[kind].core_fields if name not in fields]
        if lacking:
            raise PluginError(f"config {spec.config.__name__} has no field {lacking[0]!r}; the config of a {kind} "
                              f"subclasses the kind's base config (gpnerf_core.ModelConfig)")
        missing_default = [n for n, f in fields.items() if f.default is dataclasses.MISSING
                           and f.default_factory is dataclasses.MISSING]
        if missing_default:
            raise PluginError(f"config {spec.config.__name__}.{missing_default[0]} has no default (Hydra needs one)")
        factory = spec.factory
        if inspect.isclass(factory):
            interface = KINDS[kind].interface
            if not issubclass(factory, interface):
                raise PluginError(f"{factory.__name__} does not subclass {interface.__module__}.{interface.__name__}")
            if inspect.isabstract(factory):
                members = ", ".join(sorted(factory.__abstractmethods__))
                raise PluginError(f"{factory.__name__} leaves abstract members unimplemented: {members}")
            built_class: type | None = factory
        elif not callable(factory):
            raise PluginError(f"factory {factory!r} is not callable")
        else:
            built_class = _check_returned_class(factory, KINDS[kind].interface)
        if kind == "model" and built_class is not None:
            problems = capability_problems(built_class)
            if problems:
                raise PluginError(f"its capabilities do not hold: {problems[0]}"
                                  + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""))
        withheld = withheld_fields(kind, spec.config)
        arguments = [n for n in fields if n not in withheld] + list(KINDS[kind].runtime_arguments)
        try:
            signature = inspect.signature(factory)
        except (TypeError, ValueError):
            return  # builtins without a signature: checked when built
        try:
            signature.bind(**dict.fromkeys(arguments))
        except TypeError as exc:
            raise PluginError(
                f"factory {getattr(factory, '__name__', factory)!r} cannot be called with the config fields and the "
                f"pipeline's arguments ({', '.join(arguments) or 'none'}): {exc}"
            ) from None


def withheld_fields(kind: str, config: type) -> frozenset[str]:
    """The fields of a ``kind`` config the core keeps from the factory: the kind's (``ComponentKind.withheld``) and the
    parts a model family declares (it builds them through ``ModelParts``)."""
    return KINDS[kind].withheld | frozenset(declared_parts(config))


def _check_returned_class(factory: Any, interface: type) -> type | None:
    """A factory function whose return annotation is a class (``def build(...) -> MyFamily``, the docs' pattern):
    that class must implement ``interface`` and leave no abstract member (it would fail only when first built).
    Returns the class (None: no class annotation; checked when built)."""
    try:
        returned = typing.get_type_hints(factory).get("return")
    except Exception:  # an annotation that does not resolve here: checked when built
        return None
    if not inspect.isclass(returned):
        return None
    name = getattr(factory, "__name__", repr(factory))
    if not issubclass(returned, interface):
        raise PluginError(f"factory {name!r} returns {returned.__name__}, which does not subclass "
                          f"{interface.__module__}.{interface.__name__}")
    if inspect.isabstract(returned):
        members = ", ".join(sorted(returned.__abstractmethods__))
        raise PluginError(f"factory {name!r} returns {returned.__name__}, which leaves abstract members "
                          f"unimplemented: {members}")
    return returned


def _plain(value: Any) -> Any:
    """OmegaConf containers to plain Python, so components never see the config tree."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    if isinstance(value, (DictConfig, ListConfig)):
        return OmegaConf.to_container(value, resolve=True)
    return value


def collect(loaded: LoadedPlugins) -> Registry:
    """Call every registration hook implementation and build the registry; problems are recorded, never raised."""
    loaded.check_hooks()
    registry = Registry(problems=list(loaded.problems), plugins=dict(loaded.plugins), disabled=list(loaded.disabled))
    for kind, hook_name in ((kind.name, kind.hook) for kind in KINDS.values()):
        for impl in getattr(loaded.manager.hook, hook_name).get_hookimpls():  # registration order: stable listings
            info = loaded.plugins.get(impl.plugin_name, PluginInfo(impl.plugin_name))
            try:
                specs = impl.function()
            except Exception as exc:
                registry.problems.append(PluginProblem(info, f"{hook_name} raised {type(exc).__name__}: {one_line(exc)}"))
                continue
            if specs is not None and not isinstance(specs, (list, tuple)):
                registry.problems.append(PluginProblem(info, f"{hook_name} returned {type(specs).__name__}, expected a list"))
                continue
            for spec in specs or ():
                registry.add(kind, spec, info)
    for impl in loaded.manager.hook.gpnerf_register_data_tools.get_hookimpls():
        info = loaded.plugins.get(impl.plugin_name, PluginInfo(impl.plugin_name))
        try:
            tools = impl.function()
        except Exception as exc:
            registry.problems.append(
                PluginProblem(info, f"gpnerf_register_data_tools raised {type(exc).__name__}: {one_line(exc)}")
            )
            continue
        for tool in tools or ():
            if not isinstance(tool, DataTool):
                registry.problems.append(PluginProblem(info, f"data tool {tool!r} is not a DataTool", "data"))
            elif tool.name in registry.data_tools or f"data/{tool.name}" in registry.clashes:
                clash = registry.record_clash("data", tool.name, registry.data_tools.pop(tool.name, None), info)
                registry.problems.append(
                    PluginProblem(info, clash_message(f"data tool {tool.name!r}", clash), f"data/{tool.name}"))
            else:
                registry.data_tools[tool.name] = (tool, impl.plugin_name)
    _collect_stress_cases(loaded, registry)
    _collect_searchpaths(loaded, registry)
    return registry


SEARCHPATH_SCHEMES = ("pkg://", "file://")


def _returned(loaded: LoadedPlugins, registry: Registry, hook: str) -> Iterator[tuple[PluginInfo, str, Any]]:
    """``(plugin info, plugin name, what it returned)`` of each implementation of ``hook``; one that raises is recorded
    as a problem and left out."""
    for impl in getattr(loaded.manager.hook, hook).get_hookimpls():
        info = loaded.plugins.get(impl.plugin_name, PluginInfo(impl.plugin_name))
        try:
            returned = impl.function()
        except Exception as exc:
            registry.problems.append(PluginProblem(info, f"{hook} raised {type(exc).__name__}: {one_line(exc)}"))
            continue
        yield info, impl.plugin_name, returned


def _collect_searchpaths(loaded: LoadedPlugins, registry: Registry) -> None:
    hook = "gpnerf_config_searchpaths"
    for info, plugin_name, paths in _returned(loaded, registry, hook):
        for path in paths or ():
            if not isinstance(path, str) or not path.startswith(SEARCHPATH_SCHEMES) or not path.split("://", 1)[1]:
                registry.problems.append(PluginProblem(
                    info, f"{hook} returned {path!r}; expected a search path pkg://<package>.<folder> or "
                          "file://<absolute folder>", "config"))
            else:
                registry.config_searchpaths.append((path, plugin_name))


def _collect_stress_cases(loaded: LoadedPlugins, registry: Registry) -> None:
    for info, plugin_name, cases in _returned(loaded, registry, "gpnerf_register_stress_cases"):
        for case in cases or ():
            problem = stress_case_problem(case)
            name = getattr(case, "name", "?")
            if problem is None and (name in registry.stress_cases or f"stress/{name}" in registry.clashes):
                clash = registry.record_clash("stress", name, registry.stress_cases.pop(name, None), info)
                problem = clash_message(f"stress case {name!r}", clash)
            if problem is not None:
                registry.problems.append(PluginProblem(info, problem, f"stress/{name}"))
            else:
                registry.stress_cases[name] = (case, plugin_name)


def stress_case_problem(case: Any) -> str | None:
    """What is wrong with a registered stress case (None: nothing)."""
    if not isinstance(case, StressCase):
        return f"{case!r} is not a StressCase instance"
    if not isinstance(case.name, str) or not NAME_PATTERN.match(case.name):
        return f"name {case.name!r} is not snake_case"
    if not case.levels or not all(isinstance(v, (int, float)) for v in case.levels):
        return f"levels {case.levels!r}: expected a non-empty tuple of numbers, mildest first"
    unknown = [v for v in case.quick_levels if v not in case.levels]
    if unknown:
        return f"quick_levels has {unknown[0]!r}, which is not one of its levels {list(case.levels)}"
    if case.split not in ("train", "unseen"):
        return f"split {case.split!r}: expected train or unseen"
    return None


def register_config_options(registry: Registry) -> None:
    """Make every registered component an option of its Hydra config group (``+head=<name>``, a part's under
    ``model``: ``model/feature_extractor=<name>``).

    A model family's option carries a defaults list choosing the parts it declares (``declarations.part``) and no
    option for the part kinds it does not build, so ``model=<name>`` brings its own parts; the family's own keys come
    first (``_self_``), its parts merge into their fields. A config dataclass OmegaConf cannot represent (a field of an
    unsupported type) rejects its component.
    """
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    for kind, entries in registry.components.items():
        for name, entry in list(entries.items()):
            try:
                node = family_node(entry.spec.config) if kind == "model" else entry.spec.config
                cs.store(group=KINDS[kind].group, name=name, node=node, provider=entry.provider)
            except Exception as exc:
                del entries[name]
                info = registry.plugins.get(entry.provider, PluginInfo(entry.provider))
                reason = f"config {entry.spec.config.__name__} is not a valid Hydra schema: {one_line(exc)}"
                registry.problems.append(PluginProblem(info, reason, f"{kind}/{name}"))


def family_node(config: type) -> Any:
    """A model family's config as a Hydra option: its dataclass with a defaults list choosing its declared parts (and
    none of the part kinds it does not declare, so that every part's choice exists to interpolate)."""
    from omegaconf import OmegaConf, open_dict

    parts = declared_parts(config)
    node = OmegaConf.structured(config)
    with open_dict(node):
        node["defaults"] = ["_self_", *({kind: parts.get(kind)} for kind in PART_KINDS)]
    return node


@functools.cache
def get_registry() -> Registry:
    """The process-wide registry (built once; Hydra launcher workers rebuild it lazily)."""
    from gpnerf_core.registry.catalog import remember_registrations

    registry = collect(make_plugin_manager())
    register_config_options(registry)
    remember_registrations(registry)  # lets listing commands skip the import next time (registry.catalog)
    return registry
