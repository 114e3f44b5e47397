"""Replica scene lists (shipped split files) and frame-position rules."""

from __future__ import annotations

from importlib import resources

from gpnerf_core import ConfigError, DataError

SPLITS_PACKAGE = "gpnerf_plugins.datasets"
SPLITS_FOLDER = "splits"

PROTOCOL_FILES: dict[str, tuple[str, str]] = {
    "heldout": ("replica_train.txt", "replica_test.txt"),
    "paper_parity": ("replica_paper_train.txt", "replica_paper_test.txt"),
}
"""Protocol -> (training scene list, unseen scene list)."""

PROTOCOLS: tuple[str, ...] = tuple(PROTOCOL_FILES)
INSTANCE_SCENES_FILE = "replica_instance.txt"


def read_split_file(name: str) -> tuple[str, ...]:
    """Scene names of a shipped split file, in file order; blank lines and ``#`` comments skipped."""
    resource = resources.files(SPLITS_PACKAGE).joinpath(SPLITS_FOLDER, name)
    try:
        text = resource.read_text(encoding="utf-8")
    except (FileNotFoundError, NotADirectoryError):
        where = f"{SPLITS_PACKAGE}/{SPLITS_FOLDER}/{name}"
        raise DataError(f"{where}: split file missing from the installed package") from None
    names = tuple(line.strip() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#"))
    if not names:
        raise DataError(f"{SPLITS_PACKAGE}/{SPLITS_FOLDER}/{name}: no scene names; expected one per line")
    return names


def protocol_files(protocol: str) -> tuple[str, str]:
    """(train list, unseen list) file names of ``protocol``; ConfigError listing the choices otherwise."""
    if protocol not in PROTOCOL_FILES:
        raise ConfigError(f"dataset.protocol={protocol!r}; expected one of: {', '.join(PROTOCOLS)}")
    return PROTOCOL_FILES[protocol]


def stepped_positions(num_frames: int, start: int, stop: int, step: int, count: int = 0) -> tuple[int, ...]:
    """Positions ``range(num_frames)[start:stop:step][:count]`` (``count`` 0 = no cap), ascending."""
    positions = tuple(range(num_frames))[start:stop:step]
    return positions[:count] if count else positions


def check_frame_rule(key: str, start: int, stop: int, step: int, count: int = 0) -> None:
    """ConfigError unless ``0 <= start <= stop``, ``step >= 1`` and ``count >= 0``; ``key`` names the config fields."""
    if start < 0 or stop < start or step < 1 or count < 0:
        raise ConfigError(
            f"dataset.{key}: start={start}, stop={stop}, step={step}, count={count}; "
            "expected 0 <= start <= stop, step >= 1, count >= 0"
        )
