"""A command's outputs written all or none: each into a staging folder inside the run folder, then renamed into place
at the end, so that a failure (a full disk, an interruption) leaves none of them, half-written or whole."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable

from gpnerf_core.errors import GpnerfError

Write = Callable[[Path], Any]
"""Writes one output file at the path it is given."""


def write_staged(run_dir: Path, writes: list[tuple[str, Write]], prefix: str) -> None:
    """Run each ``(name, write)`` into the staging folder ``run_dir/<prefix>*`` (``name`` may hold one folder level,
    ``frames/0001.png``), then rename each top-level file or folder into ``run_dir``. An error names the final path,
    not the staging one; whatever was already renamed is removed again and the staging folder always is."""
    try:
        staging = Path(tempfile.mkdtemp(prefix=prefix, dir=run_dir))
    except OSError as exc:  # a full or read-only disk: name the folder it could not write into
        raise OSError(exc.errno, exc.strerror or str(exc), str(run_dir)) from None
    moved: list[Path] = []
    try:
        for name, write in writes:
            target = staging / name
            target.parent.mkdir(parents=True, exist_ok=True)
            _write_named(write, target, run_dir / name)
        for name in dict.fromkeys(name.split("/")[0] for name, _ in writes):
            (staging / name).replace(run_dir / name)
            moved.append(run_dir / name)
    except BaseException:
        for path in moved:
            shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _write_named(write: Write, target: Path, shown: Path) -> None:
    """``write(target)``; an error names ``shown`` (the file the user will look for), not the staging path."""
    try:
        write(target)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), str(shown)) from None
    except GpnerfError as exc:
        raise GpnerfError(f"{shown}: {exc}") from None
