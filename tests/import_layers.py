"""The package's import graph read from its source (ast), its layers, and the rules between them.

Run it to see the layers with their line counts, the import circles and the imports that break a rule:

    python tests/import_layers.py

Every import counts, wherever it stands: at the top of a module, inside a function (a late import that dodges a
circle at import time is still a circle in the design) or under ``if TYPE_CHECKING:``.
"""

from __future__ import annotations

import ast
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCE_ROOTS = {"gpnerf_core": ROOT / "gpnerf_core", "gpnerf_plugins": ROOT / "plugins" / "gpnerf_plugins"}

LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("foundation", ("gpnerf_core.errors", "gpnerf_core.types", "gpnerf_core.runtime", "gpnerf_core.geometry")),
    ("interfaces", ("gpnerf_core.interfaces",)),
    ("data", ("gpnerf_core.data",)),
    ("registry", ("gpnerf_core.registry",)),
    ("config", ("gpnerf_core.config",)),
    ("features", ("gpnerf_core.features",)),
    ("model", ("gpnerf_core.model",)),
    ("training", ("gpnerf_core.training",)),
    ("evaluation", ("gpnerf_core.evaluation",)),
    ("engine", ("gpnerf_core.engine",)),
    ("kit", ("gpnerf_core.testing",)),
    ("tools", ("gpnerf_core.tools",)),
    ("commands", ("gpnerf_core.commands",)),
    ("cli", ("gpnerf_core.cli", "gpnerf_core.__main__")),
    ("api", ("gpnerf_core",)),
    ("plugins", ("gpnerf_plugins",)),
)
"""From the bottom up: each layer and the folders (or root modules) it is (docs/architecture.md draws them). A module
may import its own layer and every layer below it, except: plugins import only the public surface (``api``) and each
other, exactly as a third party's package would; a command never imports another command."""

ORDER = [name for name, _ in LAYERS]
OWN_LAYER_ONLY = {"plugins": {"api", "plugins"}}
"""Layers that may import only these (instead of everything below them)."""

MAY_IMPORT: dict[str, set[str]] = {
    name: OWN_LAYER_ONLY.get(name, set(ORDER[: index + 1])) for index, name in enumerate(ORDER)
}
"""Which layers a module of each layer may import."""


def layer_of(module: str) -> str:
    best, length = None, -1
    for name, prefixes in LAYERS:
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > length:
                best, length = name, len(prefix)
    if best is None:
        raise ValueError(f"{module} belongs to no layer; add its folder to LAYERS")
    return best


@dataclass(frozen=True)
class Module:
    name: str
    path: Path

    @property
    def lines(self) -> int:
        return len(self.path.read_text().splitlines())


def find_modules() -> dict[str, Module]:
    modules = {}
    for package, folder in SOURCE_ROOTS.items():
        for path in sorted(folder.rglob("*.py")):
            parts = [package, *path.relative_to(folder).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join(parts)] = Module(".".join(parts), path)
    return modules


def _resolve(name: str, modules: dict[str, Module]) -> str | None:
    """The module an imported dotted name lives in (``a.b.C`` -> ``a.b``), if it is one of ours."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def imports_of(module: Module, modules: dict[str, Module]) -> set[str]:
    """Our modules that ``module`` imports, anywhere in its body."""
    tree = ast.parse(module.path.read_text(), filename=str(module.path))
    is_package = module.path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.name.split(".")
                base = base if is_package else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                origin = ".".join([*base, *([node.module] if node.module else [])])
            else:
                origin = node.module or ""
            names = [f"{origin}.{alias.name}" for alias in node.names] or [origin]
            names = [n if n in modules else origin for n in names]
        for name in names:
            target = _resolve(name, modules)
            if target is not None and target != module.name:
                found.add(target)
    return found


def import_graph() -> tuple[dict[str, Module], dict[str, set[str]]]:
    modules = find_modules()
    return modules, {name: imports_of(module, modules) for name, module in modules.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected groups of two or more modules (Tarjan), each sorted; none in a layered package."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))
    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def circle_edges(group: list[str], graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    members = set(group)
    return [(a, b) for a in group for b in sorted(graph[a]) if b in members]


def broken_rules(modules: dict[str, Module], graph: dict[str, set[str]]) -> list[str]:
    """One line per import that goes against ``MAY_IMPORT``, naming both files."""
    problems = []
    for name, targets in sorted(graph.items()):
        layer = layer_of(name)
        for target in sorted(targets):
            other = layer_of(target)
            command_to_command = layer == other == "commands" and name != "gpnerf_core.commands" and target != "gpnerf_core.commands"
            if other not in MAY_IMPORT[layer] or command_to_command:
                problems.append(f"{_file(modules[name])} ({layer}) imports {_file(modules[target])} ({other})")
    return problems


def _file(module: Module) -> str:
    return str(module.path.relative_to(ROOT))


def main() -> int:
    modules, graph = import_graph()
    print("layers (bottom up): modules, lines")
    for layer in ORDER:
        members = [m for m in modules.values() if layer_of(m.name) == layer]
        print(f"  {layer:<9} {len(members):>4} {sum(m.lines for m in members):>7}   may import: "
              f"{', '.join(sorted(MAY_IMPORT[layer]))}")
    groups = circles(graph)
    print(f"import circles: {len(groups)}")
    for group in groups:
        print("  " + "; ".join(f"{a} -> {b}" for a, b in circle_edges(group, graph)))
    problems = broken_rules(modules, graph)
    print(f"imports against the layers: {len(problems)}")
    for problem in problems:
        print(f"  {problem}")
    return 1 if groups or problems else 0


if __name__ == "__main__":
    sys.exit(main())
