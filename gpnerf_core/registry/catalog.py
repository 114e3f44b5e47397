"""What each entry-point plugin registers, remembered between commands, so that the commands which only list or
dispatch (``data``, ``data <tool>``, ``stress --list``) do not import a third-party plugin they do not use.

After every full load (``components.get_registry``) the names each entry-point plugin registers are written to
``$GPNERF_CACHE/plugin_index.json`` (default ``~/.cache/gpnerf``) under the plugin's fingerprint: its distribution,
version, entry point, and the size and modification time of the module the entry point names (so editing an
editable install's plugin module makes its record stale). A listing command imports the built-in plugins (gpnerf-core's
own) and reads the index; one entry point without a fresh record, or a name two plugins share, makes it load every
plugin as before. The index is a cache: unreadable or unwritable, it is ignored.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

INDEX_FILE = "plugin_index.json"
CACHE_ENV = "GPNERF_CACHE"


def index_path() -> Path:
    """``$GPNERF_CACHE/plugin_index.json`` (default ``~/.cache/gpnerf``)."""
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "gpnerf") / INDEX_FILE


def module_file(module: str) -> Path | None:
    """The source file of ``module`` (``pkg.sub.plugin``) found without importing it or its packages; None when it
    cannot be found that way (a namespace or zip import, a C module)."""
    top, *rest = module.split(".")
    try:
        spec = importlib.util.find_spec(top)  # a top-level name: nothing is imported
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    if not rest:
        return Path(spec.origin) if spec.origin and Path(spec.origin).is_file() else None
    for base in spec.submodule_search_locations or ():
        for candidate in (Path(base, *rest).with_suffix(".py"), Path(base, *rest, "__init__.py")):
            if candidate.is_file():
                return candidate
    return None


def fingerprint(entry_point: importlib.metadata.EntryPoint) -> str | None:
    """``dist==version|name=value|size:mtime_ns`` of an entry point (None: its module file cannot be found)."""
    source = module_file(entry_point.module)
    if source is None:
        return None
    stat = source.stat()
    dist = entry_point.dist
    owner = f"{dist.name}=={dist.version}" if dist is not None else "unknown"
    return f"{owner}|{entry_point.name}={entry_point.value}|{stat.st_size}:{stat.st_mtime_ns}"


@dataclass
class PluginRecord:
    """What one plugin registers: component names by kind, data tools (name -> description), stress cases (name ->
    ``[description, levels as stress --list shows them]``)."""

    components: dict[str, list[str]] = field(default_factory=dict)
    data_tools: dict[str, str] = field(default_factory=dict)
    stress_cases: dict[str, list[str]] = field(default_factory=dict)

    def names(self) -> set[str]:
        """``kind/name`` of everything it registers (``data/<tool>``, ``stress/<case>`` included)."""
        return ({f"{kind}/{name}" for kind, names in self.components.items() for name in names}
                | {f"data/{name}" for name in self.data_tools} | {f"stress/{name}" for name in self.stress_cases})


def read_index() -> dict[str, dict[str, Any]]:
    try:
        loaded = json.loads(index_path().read_text())
    except (OSError, ValueError):
        return {}
    return loaded if isinstance(loaded, dict) else {}


def remember(records: dict[str, PluginRecord]) -> None:
    """Store ``fingerprint -> record`` (merged into the index; the index only grows by what this load saw)."""
    if not records:
        return
    index = read_index()
    fresh = {key: {"components": r.components, "data_tools": r.data_tools, "stress_cases": r.stress_cases}
             for key, r in records.items()}
    if all(index.get(key) == value for key, value in fresh.items()):
        return
    from gpnerf_core.runtime.io import atomic_write_json

    try:
        index_path().parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(index_path(), {**index, **fresh})
    except OSError:
        pass  # a cache: a read-only home folder only costs the next listing an import


def cached_records(entry_points: list[importlib.metadata.EntryPoint]) -> dict[str, PluginRecord] | None:
    """The record of each entry point (by entry-point name), or None when one of them has no fresh record."""
    index = read_index()
    records = {}
    for entry_point in entry_points:
        key = fingerprint(entry_point)
        stored = index.get(key) if key is not None else None
        if not isinstance(stored, dict):
            return None
        try:
            records[entry_point.name] = PluginRecord(
                components={str(k): [str(n) for n in v] for k, v in dict(stored.get("components", {})).items()},
                data_tools={str(k): str(v) for k, v in dict(stored.get("data_tools", {})).items()},
                stress_cases={str(k): [str(v[0]), str(v[1])] for k, v in dict(stored.get("stress_cases", {})).items()},
            )
        except (TypeError, ValueError, AttributeError, IndexError, KeyError):
            return None
    return records


def stress_levels_text(case: Any) -> str:
    """A stress case's levels as ``stress --list`` shows them."""
    return ", ".join(case.label(level) for level in case.levels)


def records_of(registry: Any, plugin_names: list[str]) -> dict[str, PluginRecord]:
    """What each of ``plugin_names`` registers in ``registry`` (a full ``Registry``), names it shares with another
    plugin (refused when chosen) included."""
    records = {name: PluginRecord() for name in plugin_names}
    for kind, entries in registry.components.items():
        for name, entry in entries.items():
            if entry.provider in records:
                records[entry.provider].components.setdefault(kind, []).append(name)
    for name, (tool, provider) in registry.data_tools.items():
        if provider in records:
            records[provider].data_tools[name] = tool.description
    for name, (case, provider) in registry.stress_cases.items():
        if provider in records:
            records[provider].stress_cases[name] = [case.description, stress_levels_text(case)]
    for key, providers in registry.clashes.items():
        kind, name = key.split("/", 1)
        for provider in {p.name for p in providers} & set(records):
            record = records[provider]
            if kind == "data":
                record.data_tools.setdefault(name, "")
            elif kind == "stress":
                record.stress_cases.setdefault(name, ["", ""])
            elif name not in record.components.get(kind, []):
                record.components.setdefault(kind, []).append(name)
    return records


def remember_registrations(registry: Any) -> None:
    """After a full load: store the record of every entry-point plugin that loaded (``plugin_index.json``)."""
    from gpnerf_core.registry.plugins import enabled_entry_points

    loaded = [ep for ep in enabled_entry_points()[0] if ep.name in registry.plugins]
    keys = {ep.name: fingerprint(ep) for ep in loaded}
    records = records_of(registry, [name for name, key in keys.items() if key is not None])
    remember({keys[name]: record for name, record in records.items()})
