"""The package stays layered (docs/architecture.md): no import circles, and no import from a lower layer to a higher
one (the model never imports the engine, a tool, a command or the CLI; a command never imports another command); the
built-in plugins, the examples and the docs import only the public surface (``gpnerf_core``, and the contract kit
``gpnerf_core.testing`` in a plugin's tests)."""

import ast
import re
from pathlib import Path

import pytest

from import_layers import (
    Module,
    broken_rules,
    circle_edges,
    circles,
    import_graph,
    imports_of,
    layer_of,
)


def test_no_module_imports_itself_back_through_others():
    _, graph = import_graph()
    found = ["; ".join(f"{a} -> {b}" for a, b in circle_edges(group, graph)) for group in circles(graph)]
    assert found == [], "import circles: " + " | ".join(found)


def test_every_import_follows_the_layers():
    modules, graph = import_graph()
    assert broken_rules(modules, graph) == []


def test_the_reader_sees_late_relative_and_type_checking_imports(tmp_path):
    """The rules are only as good as the reader: imports inside functions, relative ones and those under
    ``TYPE_CHECKING`` are all edges."""
    package = tmp_path / "gpnerf_core"
    (package / "commands").mkdir(parents=True)
    source = {
        "__init__.py": "",
        "types.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .geometry import SampledMaps\n",
        "geometry.py": "def f():\n    from gpnerf_core.types import Frame\n",
        "commands/__init__.py": "",
        "commands/run.py": "from ..jobs import launch\nfrom gpnerf_core.commands import eval as other\n",
        "commands/eval.py": "",
        "jobs.py": "",
    }
    for name, text in source.items():
        (package / name).write_text(text)
    names = {p: ".".join(["gpnerf_core", *p.relative_to(package).with_suffix("").parts]).removesuffix(".__init__")
             for p in package.rglob("*.py")}
    modules = {name: Module(name, path) for path, name in names.items()}
    graph = {name: imports_of(m, modules) for name, m in modules.items()}
    assert graph["gpnerf_core.types"] == {"gpnerf_core.geometry"}
    assert graph["gpnerf_core.geometry"] == {"gpnerf_core.types"}
    assert graph["gpnerf_core.commands.run"] == {"gpnerf_core.jobs", "gpnerf_core.commands.eval"}
    assert circles(graph) == [["gpnerf_core.geometry", "gpnerf_core.types"]]


def test_a_command_importing_another_command_or_the_model_importing_a_command_is_named():
    modules, graph = import_graph()
    bad = dict(graph)
    bad["gpnerf_core.model.build"] = graph["gpnerf_core.model.build"] | {"gpnerf_core.commands.run"}
    bad["gpnerf_core.commands.eval"] = graph["gpnerf_core.commands.eval"] | {"gpnerf_core.commands.run"}
    bad["gpnerf_plugins.heads.unet"] = graph["gpnerf_plugins.heads.unet"] | {"gpnerf_core.types"}
    problems = broken_rules(modules, bad)
    assert "gpnerf_core/model/build.py (model) imports gpnerf_core/commands/run.py (commands)" in problems
    assert "gpnerf_core/commands/eval.py (commands) imports gpnerf_core/commands/run.py (commands)" in problems
    assert "plugins/gpnerf_plugins/heads/unet.py (plugins) imports gpnerf_core/types.py (foundation)" in problems
    assert len(problems) == 3


@pytest.mark.parametrize("module,layer", [
    ("gpnerf_core.types", "foundation"), ("gpnerf_core.runtime.io", "foundation"), ("gpnerf_core.data.frames", "data"),
    ("gpnerf_core.training.trainer", "training"), ("gpnerf_plugins.heads.unet", "plugins"),
    ("gpnerf_core.tools.stress.runner", "tools"), ("gpnerf_core.engine.launching", "engine"),
    ("gpnerf_core.commands.run", "commands"), ("gpnerf_core.cli", "cli"), ("gpnerf_core", "api"),
])
def test_layer_of(module, layer):
    assert layer_of(module) == layer


def test_every_command_is_a_module_with_main():
    """``cli`` dispatches by name to ``gpnerf_core.commands.<name>.main``: each exists and takes ``argv``."""
    from gpnerf_core.cli import COMMANDS

    modules, _ = import_graph()
    for command in COMMANDS:
        module = modules.get(f"gpnerf_core.commands.{command}")
        assert module is not None, f"no gpnerf_core/commands/{command}.py"
        mains = [n for n in ast.parse(module.path.read_text()).body if isinstance(n, ast.FunctionDef) and n.name == "main"]
        assert mains and [a.arg for a in mains[0].args.args] == ["argv"], f"{command}: expected main(argv)"


ROOT = Path(__file__).resolve().parents[1]
PRIVATE_IMPORT = re.compile(r"^\s*(?:from|import) (gpnerf_core\.[\w.]+)", re.M)


@pytest.mark.parametrize("folder", ["examples", "docs"])
def test_examples_and_docs_import_only_the_public_surface(folder):
    """What a user copies imports ``gpnerf_core`` (or the contract kit, ``gpnerf_core.testing``), never an engine
    module that may move."""
    found = []
    for path in sorted((ROOT / folder).rglob("*")):
        if path.suffix not in (".py", ".md") or not path.is_file():
            continue
        for module in PRIVATE_IMPORT.findall(path.read_text()):
            if not module.startswith("gpnerf_core.testing"):
                found.append(f"{path.relative_to(ROOT)}: {module}")
    assert found == []


def test_the_package_root_holds_only_a_handful_of_modules():
    """Everything else lives in a package that says what it is (docs/architecture.md)."""
    root = sorted(p.name for p in (ROOT / "gpnerf_core").glob("*.py"))
    assert root == ["__init__.py", "__main__.py", "cli.py", "errors.py", "types.py"]
