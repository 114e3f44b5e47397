"""``python -m gpnerf_core plugins``: registered components (kind, name, provider, version, description), disabled
plugins and the problems of plugins that failed; exit code 1 when there are problems."""

from __future__ import annotations

from gpnerf_core.config.presets import preset_clashes
from gpnerf_core.errors import GpnerfError
from gpnerf_core.registry.components import get_registry


USAGE = """usage: python -m gpnerf_core plugins

Lists every registered component (kind, name, provider, version, description) and stress case, the config folders
plugins ship (their presets), the plugins disabled by GPNERF_DISABLE_PLUGINS / GPNERF_DISABLE_PLUGIN_AUTOLOAD, and the
problems of plugins that failed to load or whose components were rejected (a name two plugins register is one: choosing
it is refused until all but one are disabled; so is a plugin's preset with the path of a built-in or another plugin's).
Exit code 0, or 1 when there are problems."""


def main(argv: list[str]) -> int:
    if argv in (["-h"], ["--help"]):
        print(USAGE)
        return 0
    if argv:
        raise GpnerfError(f"plugins takes no arguments (or --help), got {' '.join(argv)!r}")
    registry = get_registry()
    rows = [("kind", "name", "provider", "version", "description")]
    for kind, entries in registry.components.items():
        for name in sorted(entries):
            entry = entries[name]
            rows.append((kind, name, entry.provider, entry.version, entry.spec.description))
    for name, (case, provider) in registry.stress_cases.items():
        version = registry.plugins[provider].version if provider in registry.plugins else "builtin"
        rows.append(("stress_case", name, provider, version, case.description))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    for row in rows:
        print("  ".join(cell.ljust(widths[i]) for i, cell in enumerate(row[:4])) + "  " + row[4])
    if registry.config_searchpaths:
        print("\nconfig search paths:")
        for path, plugin in registry.config_searchpaths:
            print(f"  {path}  ({plugin})")
    if registry.disabled:
        print("\ndisabled:")
        for name in registry.disabled:
            print(f"  {name}")
    problems = [str(problem) for problem in registry.problems] + preset_clashes(registry)
    if problems:
        print("\nproblems:")
        for problem in problems:
            print(f"  {problem}")
        return 1
    return 0
