"""Hydra override strings as typed on the command line: their keys, and which of them belong to one run only.

String handling (Hydra's override parser decides what needs quotes), shared by the job lifecycle (``engine``), the
commands that recompose a checkpoint's config (``eval``, ``finetune``, ``render``) and the tools that launch runs of
their own (``size``).
"""

from __future__ import annotations

import re

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
    (``head=per_pixel`` after ``+head=unet``). ``~key`` drops the checkpoint's override of ``key``. A command that
    chooses another dataset drops the checkpoint's ``dataset.*`` options (``foreign_dataset_note`` says so). Flags
    (``-m``) keep their place in front.
    """
    flags = [a for a in given if a.startswith("-")]
    overrides = [a for a in given if not a.startswith("-")]
    foreign = foreign_dataset_options(stored, overrides)
    stored = [o for o in stored if o not in foreign]
    user_keys = {override_key(o) for o in overrides}
    # ``~key`` of a key the checkpoint set only drops the checkpoint's override (Hydra may not delete a schema field)
    stored_keys = {override_key(o) for o in stored}
    overrides = [o for o in overrides if not (o.startswith("~") and override_key(o) in stored_keys)]
    added = {override_key(o) for o in stored if o.startswith("+") and not o.startswith("++")}
    kept = [o for o in stored if override_key(o) not in user_keys and override_key(o) not in RUN_SPECIFIC_KEYS]
    adjusted = [f"+{o}" if override_key(o) in added and not o.startswith(("+", "~")) else o for o in overrides]
    return [*flags, *kept, *adjusted]


def dataset_choice(overrides: list[str]) -> str | None:
    """The dataset ``overrides`` choose (the last ``dataset=<name>``), or None: the config's default."""
    chosen = None
    for override in overrides:
        if override_key(override) == "dataset" and not override.startswith("~") and "=" in override:
            chosen = override.split("=", 1)[1]
    return chosen


def default_choice(group: str) -> str:
    """The option of ``group`` the primary config's defaults list chooses (``conf/config.yaml``: ``model``,
    ``dataset``, ...): where the built-in defaults are declared, so no tool names them."""
    from omegaconf import OmegaConf

    from gpnerf_core.config.compose import config_dir

    defaults = OmegaConf.load(f"{config_dir()}/config.yaml").defaults
    return next(str(entry[group]) for entry in defaults if not isinstance(entry, str) and group in entry)


def default_dataset() -> str:
    """The dataset of the primary config's defaults list (``conf/config.yaml``)."""
    return default_choice("dataset")


def foreign_dataset_options(stored: list[str], given: list[str]) -> list[str]:
    """The ``dataset.*`` options of ``stored`` (a checkpoint's overrides) that ``given`` leaves behind by choosing
    another dataset than ``stored`` composed: those the chosen dataset's config does not have (its schema would refuse
    them). Options both datasets have (image size, frames, ...) carry over, as every other option of the checkpoint
    does. Empty when ``given`` keeps the dataset."""
    chosen = dataset_choice(given)
    if chosen is None or chosen == (dataset_choice(stored) or default_dataset()):
        return []
    options = _dataset_options(chosen)
    return [o for o in stored
            if override_key(o).startswith("dataset.") and override_key(o).split(".")[1] not in options]


def _dataset_options(name: str) -> set[str]:
    """The top-level options of dataset ``name``'s config (none for a dataset no plugin registers: it is refused)."""
    import dataclasses

    from gpnerf_core.registry.components import get_registry

    entry = get_registry().components.get("dataset", {}).get(name)
    return {field.name for field in dataclasses.fields(entry.spec.config)} if entry is not None else set()


def foreign_dataset_note(stored: list[str], given: list[str]) -> str | None:
    """The note a command prints when ``merge_overrides(stored, given)`` left the checkpoint's dataset options behind
    (``given`` may be the merged overrides: they choose the same dataset); None when it left none."""
    dropped = foreign_dataset_options(stored, given)
    if not dropped:
        return None
    trained_on = dataset_choice(stored) or default_dataset()
    return (f"dataset={dataset_choice(given)} is not the checkpoint's dataset ({trained_on}): its options "
            f"{', '.join(dropped)} are not options of {dataset_choice(given)} and are not carried over")


def quoted_for_hydra(override: str) -> str:
    """``key=value`` with a value Hydra's override grammar cannot read unquoted (a path with ``=``, ``#``, ``&``,
    ``~``, ``!``, brackets or parentheses in it, non-ASCII letters, spaces) put in single quotes, so it is taken as the
    literal string it was typed as; every other argument unchanged (flags, sweeps ``a,b``, lists, interpolations,
    quoted values, values Hydra reads as they are)."""
    key, sep, value = override.partition("=")
    if not sep or key.startswith("-") or not value or value[0] in "'\"[{" or "${" in value:
        return override
    if value.isascii() and " " not in value and _hydra_reads(override):
        return override
    if re.fullmatch(r"\w+\(.*\)", value):  # a sweep function (choice, range, ...) Hydra names in its own error
        return override
    quoted = f"{key}={hydra_quoted(value)}"
    return quoted if _hydra_reads(quoted) else override


def hydra_quoted(value: str) -> str:
    """``value`` in single quotes as Hydra's grammar reads it back: quotes escaped, and the backslashes before a quote
    or at the end doubled (Hydra keeps every other backslash as it is)."""
    escaped = re.sub(r"(\\+)(?='|$)", lambda match: match.group(1) * 2, value).replace("'", "\\'")
    return f"'{escaped}'"


def _hydra_reads(override: str) -> bool:
    """True when Hydra's override grammar parses ``override``."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        OverridesParser.create().parse_override(override)
    except Exception:
        return False
    return True
