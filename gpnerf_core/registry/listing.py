"""What the built-in plugins and the plugin index (``registry.catalog``) register, for the commands that only list
or dispatch (``data``, ``stress --list``): no third-party plugin is imported where the index knows them all."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gpnerf_core.registry.catalog import PluginRecord, cached_records, stress_levels_text
from gpnerf_core.registry.components import collect
from gpnerf_core.registry.plugins import enabled_entry_points, make_plugin_manager


@dataclass(frozen=True)
class Listing:
    """What the built-in plugins and the indexed entry points register, for commands that only list or dispatch.

    Attributes:
        builtin: the registry of the built-in plugins alone (imported).
        plugins: entry-point name -> its record (from the index; nothing imported).
    """

    builtin: Any
    plugins: dict[str, PluginRecord]

    def data_tools(self) -> dict[str, tuple[str, str]]:
        """``name -> (description, plugin)`` over built-ins and indexed plugins."""
        tools = {name: (tool.description, provider) for name, (tool, provider) in self.builtin.data_tools.items()}
        for plugin, record in self.plugins.items():
            tools.update({name: (description, plugin) for name, description in record.data_tools.items()})
        return dict(sorted(tools.items()))

    def stress_cases(self) -> dict[str, tuple[str, str, str]]:
        """``name -> (description, levels text, plugin)`` over built-ins and indexed plugins."""
        cases = {name: (case.description, stress_levels_text(case), provider)
                 for name, (case, provider) in self.builtin.stress_cases.items()}
        for plugin, record in self.plugins.items():
            cases.update({name: (text[0], text[1], plugin) for name, text in record.stress_cases.items()})
        return cases

    def unshared_builtin_tool(self, name: str) -> Any | None:
        """The built-in data tool ``name`` when no indexed plugin registers that name too (else None)."""
        if name not in self.builtin.data_tools or f"data/{name}" in self.builtin.clashes:
            return None
        if any(f"data/{name}" in record.names() for record in self.plugins.values()):
            return None
        return self.builtin.data_tools[name][0]

    @property
    def unambiguous(self) -> bool:
        """No name registered twice over the built-ins and the indexed plugins (a clash needs the full load's
        message)."""
        seen: set[str] = set()
        builtin_names = ({f"{kind}/{name}" for kind, entries in self.builtin.components.items() for name in entries}
                         | {f"data/{name}" for name in self.builtin.data_tools}
                         | {f"stress/{name}" for name in self.builtin.stress_cases} | set(self.builtin.clashes))
        for names in (builtin_names, *(record.names() for record in self.plugins.values())):
            if seen & names:
                return False
            seen |= names
        return True


def listing() -> Listing | None:
    """The ``Listing`` of this environment, or None when a full load is needed: an enabled entry point without a
    fresh record in the index, or a name registered twice."""
    records = cached_records(enabled_entry_points()[0])
    if records is None:
        return None
    found = Listing(collect(make_plugin_manager(autoload=False)), records)
    return found if found.unambiguous else None
