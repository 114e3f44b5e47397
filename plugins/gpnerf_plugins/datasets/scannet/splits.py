"""The shipped ScanNet scene lists (``splits/scannet_{train,test,val}.txt``, the reference's split files)."""

from __future__ import annotations

from importlib import resources

from gpnerf_core import ConfigError, DataError
from gpnerf_plugins.datasets.scannet.files import SCENE_NAME

SPLIT_FILES = {"train": "scannet_train.txt", "test": "scannet_test.txt", "val": "scannet_val.txt"}


def read_split(name: str) -> tuple[str, ...]:
    """Scene names of a shipped split file: ``train`` (198), ``test`` (10, the unseen scenes) or ``val`` (3).

    Lines starting with ``#`` are comments. Raises ``DataError`` for a malformed or duplicated entry.
    """
    if name not in SPLIT_FILES:
        raise ConfigError(f"unknown ScanNet split file {name!r}; expected one of: {', '.join(SPLIT_FILES)}")
    resource = resources.files("gpnerf_plugins.datasets").joinpath("splits", SPLIT_FILES[name])
    try:
        text = resource.read_text(encoding="utf-8")
    except OSError as exc:
        message = f"{resource}: unreadable ({exc}); expected the split file shipped with gpnerf_plugins"
        raise DataError(message) from None
    scenes: list[str] = []
    for line_no, line in enumerate(text.splitlines(), start=1):
        entry = line.strip()
        if not entry or entry.startswith("#"):
            continue
        if not SCENE_NAME.match(entry):
            raise DataError(f"{resource}:{line_no}: {entry!r}; expected a scene name sceneXXXX_YY")
        if entry in scenes:
            raise DataError(f"{resource}:{line_no}: {entry} listed twice; expected each scene once")
        scenes.append(entry)
    return tuple(scenes)
