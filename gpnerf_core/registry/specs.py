"""The records a plugin's hooks return: a component it offers (``ComponentSpec``) and a ``data`` tool (``DataTool``).

They sit below both the hook specifications (``hookspecs``), which name them as return types, and the registry,
which collects them, so neither of those imports the other for them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping


@dataclass(frozen=True)
class ComponentSpec:
    """A component a plugin offers.

    Attributes:
        name: registry key and Hydra option name (snake_case).
        factory: called as ``factory(**config_fields_without_name, **runtime_kwargs)``.
        config: a dataclass type whose fields are the factory's keyword arguments; its ``name`` field
            must default to ``name``. It becomes the Hydra option's schema.
        description: one line shown by ``python -m gpnerf_core plugins``.
        display_name: what ``report`` calls the method a model family's runs are: a name (``"Semantic-Ray"``; a run
            with a ``+head`` is then ``"<name> + <head> head"``), or a function of a run's config (plain dicts: its
            ``model`` section, ``head``, ``loss``, ...) returning the whole name, for a family whose name depends on
            its options (GP-NeRF's field without semantics is ``"GNT"``). "" = the registry name. Read only for the
            ``model`` kind.
    """

    name: str
    factory: Callable[..., Any]
    config: type
    description: str = ""
    display_name: str | Callable[[Mapping[str, Any]], str] = ""


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
