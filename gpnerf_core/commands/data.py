"""``python -m gpnerf_core data <tool> [arguments]``: the dataset tools plugins register (check a layout, prepare
ScanNet, make the embedded scenes, ...); ``data`` alone lists them."""

from __future__ import annotations

from gpnerf_core.errors import GpnerfError
from gpnerf_core.registry.components import clash_message, get_registry


def main(argv: list[str]) -> int:
    tools = get_registry().data_tools
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m gpnerf_core data <tool> [arguments]\n\ntools:")
        for name in sorted(tools):
            print(f"  {name:<18} {tools[name][0].description}")
        return 0
    clash = get_registry().clashes.get(f"data/{argv[0]}")
    if clash is not None:
        raise GpnerfError(clash_message(f"data tool {argv[0]!r}", clash))
    if argv[0] not in tools:
        raise GpnerfError(f"unknown data tool {argv[0]!r}; known tools: {', '.join(sorted(tools)) or '(none)'}")
    return int(tools[argv[0]][0].run(argv[1:]) or 0)
