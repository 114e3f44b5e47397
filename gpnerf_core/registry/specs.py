"""The records a plugin's hooks return: a component it offers (``ComponentSpec``) and a ``data`` tool (``DataTool``).

They sit below both the hook specifications (``hookspecs``), which name them as return types, and the registry,
which collects them, so neither of those imports the other for them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable


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
