"""The core's tools, engine, config and contract kit name no built-in model family or part: they read what a component
declares (the parts a family builds, its learning-rate groups, its size knobs, its display name), so a third party's
family is read the same way. The one exception is a declared default, ``config.legacy.DEFAULT_MODEL`` (the family of
configs written before ``model`` named one); the primary config's defaults live in ``conf/config.yaml``."""

import re
from pathlib import Path

from gpnerf_core.registry.components import collect
from gpnerf_core.registry.kinds import PART_KINDS
from gpnerf_core.registry.plugins import make_plugin_manager

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("gpnerf_core/tools", "gpnerf_core/engine", "gpnerf_core/config", "gpnerf_core/testing")
DECLARED_DEFAULTS = {("gpnerf_core/config/legacy.py", 'DEFAULT_MODEL = "gnt"')}
"""``(file, line)``: where a built-in name is the declared default."""


def builtin_names() -> list[str]:
    """The registry names of the built-in model families and parts."""
    registry = collect(make_plugin_manager(autoload=False))
    return sorted({name for kind in ("model", *PART_KINDS) for name in registry.names(kind)})


def test_the_names_looked_for_are_the_built_in_families_and_parts():
    assert {"gnt", "mvsplat", "semantic_3dgs", "mvsnerf", "neuray", "semantic_ray", "semantic_nerf", "dm_nerf",
            "resunet_fpn", "mvsnet", "gnt_view", "gnt_ray"} <= set(builtin_names())


def test_tools_engine_config_and_the_kit_name_no_built_in_family_or_part():
    pattern = re.compile(r"\b(" + "|".join(map(re.escape, builtin_names())) + r")\b")
    found = []
    for folder in SCANNED:
        for path in sorted((ROOT / folder).rglob("*.py")):
            relative = path.relative_to(ROOT).as_posix()
            for number, line in enumerate(path.read_text().splitlines(), 1):
                if pattern.search(line) and (relative, line.strip()) not in DECLARED_DEFAULTS:
                    found.append(f"{relative}:{number}: {line.strip()}")
    assert not found, "built-in names where declarations should be read:\n" + "\n".join(found)
