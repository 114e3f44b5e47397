"""The output folder of ``data import-colmap`` and ``data prepare-capture``: checked before any work, built in a hidden
temporary folder beside it and renamed into place at the end, so an error or Ctrl-C leaves nothing half-written.

The temporary folder ``.<name>.partial-XXXX`` holds ``scene/`` (what becomes ``--out``) and ``scratch/`` (working
files: extracted frames, the COLMAP database, sparse models); it is deleted whatever happens.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from gpnerf_core import DataError


def check_destination(out: Path, *, overwrite: bool, inputs: Sequence[Path] = ()) -> Path:
    """``out`` made absolute, after refusing a destination that cannot or must not be written.

    Raises:
        DataError: a path above ``out`` is a file; ``out`` is a file; ``out`` is or holds one of ``inputs`` (the
            user's files are never replaced); ``out`` is a non-empty folder and ``overwrite`` is false.
    """
    out = Path(out).expanduser().absolute()
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise DataError(f"--out {out}: {parent} is a file; expected --out to name a folder")
            break
    if out.exists() and not out.is_dir():
        raise DataError(f"--out {out}: is a file; expected a new or empty folder")
    resolved = out.resolve()
    for source in inputs:
        source = Path(source).expanduser().resolve()
        if source == resolved or resolved in source.parents:
            raise DataError(f"--out {out}: holds the input {source}; expected a folder outside the inputs")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise DataError(f"--out {out}: exists and is not empty; expected a new folder (pass --overwrite to replace it)")
    return out


@dataclass(frozen=True)
class Stage:
    """``scene``: the folder that becomes ``--out``; ``scratch``: working files, deleted at the end."""

    scene: Path
    scratch: Path


@contextmanager
def staged(out: Path) -> Iterator[Stage]:
    """Yield empty ``scene`` and ``scratch`` folders beside ``out``; ``scene`` replaces ``out`` when the block ends
    without an error (an existing ``out`` is removed only then). On any error, ``KeyboardInterrupt`` included, the
    temporary folder is deleted and ``out`` is left as it was."""
    out.parent.mkdir(parents=True, exist_ok=True)
    temporary = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        stage = Stage(temporary / "scene", temporary / "scratch")
        stage.scene.mkdir()  # a plain mkdir: the scene gets the usual permissions, not mkdtemp's 0700
        stage.scratch.mkdir()
        yield stage
        replaced = None
        if out.exists():
            replaced = temporary / "replaced"
            out.rename(replaced)
        try:
            stage.scene.rename(out)
        except BaseException:
            if replaced is not None:
                replaced.rename(out)
            raise
    finally:
        shutil.rmtree(temporary, ignore_errors=True)
