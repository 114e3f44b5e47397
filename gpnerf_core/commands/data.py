"""``python -m gpnerf_core data <tool> [arguments]``: the dataset tools plugins register (check a layout, prepare
ScanNet, make the embedded scenes, ...); ``data`` alone lists them.

Listing, and running a built-in tool no other plugin registers, import no third-party plugin where the plugin index
knows what each registers (``gpnerf_core.registry.listing``); anything else loads every plugin.
"""

from __future__ import annotations

from gpnerf_core.errors import GpnerfError
from gpnerf_core.registry.listing import listing
from gpnerf_core.registry.components import clash_message, get_registry


def main(argv: list[str]) -> int:
    known = listing()
    if not argv or argv[0] in ("-h", "--help"):
        tools = known.data_tools() if known is not None else {
            name: (tool.description, provider) for name, (tool, provider) in sorted(get_registry().data_tools.items())
        }
        print("usage: python -m gpnerf_core data <tool> [arguments]\n\ntools:")
        for name, (description, _) in tools.items():
            print(f"  {name:<18} {description}")
        return 0
    builtin = known.unshared_builtin_tool(argv[0]) if known is not None else None
    if builtin is not None:
        return int(builtin.run(argv[1:]) or 0)
    tools = get_registry().data_tools
    clash = get_registry().clashes.get(f"data/{argv[0]}")
    if clash is not None:
        raise GpnerfError(clash_message(f"data tool {argv[0]!r}", clash))
    if argv[0] not in tools:
        raise GpnerfError(f"unknown data tool {argv[0]!r}; known tools: {', '.join(sorted(tools)) or '(none)'}")
    return int(tools[argv[0]][0].run(argv[1:]) or 0)
