"""Scene lists a user gives (``dataset.scenes``, ``dataset.unseen_scenes``) in place of a dataset's shipped ones."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from gpnerf_core import ConfigError, DataError

SHOWN = 12  # folder names listed in a missing-scene error


def chosen_scenes(key: str, names: Sequence[str], shipped: tuple[str, ...]) -> tuple[str, ...]:
    """``names`` (the user's ``dataset.<key>``) if given, else ``shipped``; names must be plain, distinct folder names."""
    names = tuple(str(name) for name in names)
    for name in names:
        if not name or name in (".", "..") or "/" in name or "\\" in name:
            raise ConfigError(f"dataset.{key} has {name!r}; expected folder names directly under dataset.root")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ConfigError(f"dataset.{key} names {repeated[0]!r} twice; expected each scene once")
    return names or shipped


def disjoint_unseen(
    train: tuple[str, ...], unseen: tuple[str, ...], *, train_given: bool, unseen_given: bool
) -> tuple[str, ...]:
    """The unseen scenes, given the training scenes.

    Both lists given and sharing a scene: ConfigError. Only ``dataset.scenes`` given: the scenes chosen for training
    leave the shipped unseen list (fine-tuning on an unseen scene). Neither given: the shipped lists as they are.
    """
    shared = [name for name in train if name in unseen]
    if not shared:
        return unseen
    if unseen_given:
        raise ConfigError(
            f"scene {shared[0]!r} is in both dataset.scenes and dataset.unseen_scenes; a scene is either trained on "
            "or unseen"
        )
    if train_given:
        return tuple(name for name in unseen if name not in train)
    return unseen


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
