"""Hydra override strings as typed on the command line: their keys, and which of them belong to one run only.

Pure string handling, shared by the job lifecycle (``jobs``), the commands that recompose a checkpoint's config
(``eval``, ``finetune``, ``render``) and the tools that launch runs of their own (``size``).
"""

from __future__ import annotations

RUN_SPECIFIC_KEYS = ("checkpoint", "out_dir", "overwrite", "train.resume")
"""Overrides that name this run's files, not its model: never carried from a checkpoint into another run."""


def override_key(override: str) -> str:
    """``+head=unet`` -> ``head``; ``train.steps=10`` -> ``train.steps``."""
    return override.split("=", 1)[0].lstrip("+~")


def is_search_path(override: str) -> bool:
    """``hydra.searchpath=[file://<dir>]``: where ``+experiment=<name>`` finds a config written outside the package
    (``size``'s ``experiment/sized.yaml``); it changes what composes, so it is kept wherever the config is composed."""
    return override.lstrip("+~").startswith("hydra.searchpath=")


def merge_overrides(stored: list[str], given: list[str]) -> list[str]:
    """A checkpoint's overrides (minus run-specific ones) followed by the command's; the command's win.

    A group the checkpoint added with ``+`` stays added when the command switches it without ``+``
    (``head=per_pixel`` after ``+head=unet``). Flags (``-m``) keep their place in front.
    """
    flags = [a for a in given if a.startswith("-")]
    overrides = [a for a in given if not a.startswith("-")]
    user_keys = {override_key(o) for o in overrides}
    added = {override_key(o) for o in stored if o.startswith("+") and not o.startswith("++")}
    kept = [o for o in stored if override_key(o) not in user_keys and override_key(o) not in RUN_SPECIFIC_KEYS]
    adjusted = [f"+{o}" if override_key(o) in added and not o.startswith(("+", "~")) else o for o in overrides]
    return [*flags, *kept, *adjusted]


def quoted_for_hydra(override: str) -> str:
    """``key=value`` with a value Hydra's override grammar cannot read unquoted (a path with non-ASCII letters or
    spaces) put in single quotes; every other argument unchanged (flags, lists, interpolations, quoted values)."""
    key, sep, value = override.partition("=")
    if not sep or key.startswith("-") or not value or value[0] in "'\"[{" or "${" in value:
        return override
    if value.isascii() and " " not in value:
        return override
    escaped = value.replace("\\", "\\\\").replace("'", "\\'")
    return f"{key}='{escaped}'"
