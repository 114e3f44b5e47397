"""Scene lists a user gives (``dataset.scenes``, ``dataset.unseen_scenes``) in place of a dataset's shipped ones."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from gpnerf_core import ConfigError, DataError

SHOWN = 12  # folder names listed in a missing-scene error


def chosen_scenes(key: str, names: Sequence[str] | None, shipped: tuple[str, ...]) -> tuple[str, ...]:
    """``names`` (the user's ``dataset.<key>``) if given, else ``shipped``; names must be plain, distinct folder names."""
    names = tuple(str(name) for name in names or ())
    for name in names:
        if not name or name in (".", "..") or "/" in name or "\\" in name:
            raise ConfigError(f"dataset.{key} has {name!r}; expected folder names directly under dataset.root")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ConfigError(f"dataset.{key} names {repeated[0]!r} twice; expected each scene once")
    return names or shipped


def chosen_unseen(
    names: Sequence[str] | None,
    shipped: tuple[str, ...],
    *,
    train: tuple[str, ...],
    train_given: bool,
    shipped_train: tuple[str, ...] = (),
) -> tuple[str, ...]:
    """The unseen scenes (``dataset.unseen_scenes``), given the training scenes ``train``: the one rule of every dataset.

    Args:
        names: ``dataset.unseen_scenes``: a list names the unseen scenes (``[]`` = none); None (the default) means the
            dataset's shipped unseen list ``shipped``, less the scenes ``dataset.scenes`` trains on (fine-tuning on a
            shipped unseen scene), and none at all when ``dataset.scenes`` names no shipped scene (``shipped`` or
            ``shipped_train``): a folder of the user's own scenes, where a shipped scene is not there to read.
        train_given: ``dataset.scenes`` was given (else ``train`` is the shipped training list, kept as it is, a
            protocol's leak of unseen scenes into training included).

    Raises:
        ConfigError: a named unseen scene is also trained on, or a name is not a plain, distinct folder name.
    """
    if names is not None:
        unseen = chosen_scenes("unseen_scenes", names, ())
        shared = [name for name in train if name in unseen]
        if shared:
            raise ConfigError(
                f"scene {shared[0]!r} is in both dataset.scenes and dataset.unseen_scenes; a scene is either trained "
                "on or unseen (dataset.unseen_scenes=[] for none)"
            )
        return unseen
    if not train_given:
        return shipped
    if not any(name in shipped or name in shipped_train for name in train):
        return ()  # the user's own scenes: no shipped scene is theirs to read
    return tuple(name for name in shipped if name not in train)


def present_folders(root: Path) -> str:
    """The folder names under ``root``, for an error message (the first few, sorted, with a count)."""
    try:
        names = sorted(entry.name for entry in root.iterdir() if entry.is_dir() and not entry.name.startswith("."))
    except OSError:
        return "nothing readable"
    if not names:
        return "no folders"
    shown = ", ".join(names[:SHOWN])
    return shown + (f" (+{len(names) - SHOWN} more)" if len(names) > SHOWN else "")


def missing_scene(root: Path, scene: str, expected: str) -> DataError:
    """The one-line error for a scene folder that is not under ``root``, listing what is."""
    return DataError(f"{root / scene}: scene folder missing; expected {expected}; {root} holds: {present_folders(root)}")
