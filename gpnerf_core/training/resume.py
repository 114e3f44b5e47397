"""A run folder's checkpoints: which one a run resumes from (``train.resume=auto``) and which it keeps
(``train.keep_checkpoints``).

Checkpoints are ``<run>/checkpoints/step_<step>.pt``, written atomically by rank 0. "Intact" means it reads and its
contents match the hash written with it (``checkpoint.verify_content``); a damaged newest checkpoint is skipped, with
a note naming it, for the one before it.
"""

from __future__ import annotations

import re
from pathlib import Path

from gpnerf_core.errors import DataError
from gpnerf_core.model.trained import load_trained

CHECKPOINT_NAME = re.compile(r"^step_(\d+)\.pt$")
CHECKPOINT_FOLDER = "checkpoints"


def checkpoint_path(run_dir: Path, step: int) -> Path:
    """Where the run in ``run_dir`` writes its checkpoint at ``step``."""
    return Path(run_dir) / CHECKPOINT_FOLDER / f"step_{step:07d}.pt"


def run_checkpoints(run_dir: Path) -> list[tuple[int, Path]]:
    """``(step, path)`` of every checkpoint file in ``run_dir/checkpoints``, oldest first (temporary files of an
    unfinished write are not checkpoints)."""
    folder = Path(run_dir) / CHECKPOINT_FOLDER
    if not folder.is_dir():
        return []
    found = []
    for path in folder.iterdir():
        match = CHECKPOINT_NAME.match(path.name)
        if match and path.is_file():
            found.append((int(match.group(1)), path))
    return sorted(found)


def newest_intact_checkpoint(run_dir: Path) -> tuple[Path | None, list[str]]:
    """The newest checkpoint of ``run_dir`` that reads and verifies, and one note per damaged newer one skipped.

    Raises:
        DataError: checkpoints exist but none is intact (nothing is deleted: the files may still be worth a look).
    """
    checkpoints = run_checkpoints(run_dir)
    notes = []
    for _, path in reversed(checkpoints):
        try:
            load_trained(path)  # verified here; the caller reads the one found again (only after damage)
        except DataError as exc:
            notes.append(f"skipped a damaged checkpoint: {exc}")
            continue
        return path, notes
    if checkpoints:
        raise DataError(
            f"train.resume=auto: none of the {len(checkpoints)} checkpoints in {Path(run_dir) / CHECKPOINT_FOLDER} "
            f"is intact (newest: {checkpoints[-1][1].name}); resume from one by hand or choose another out_dir"
        )
    return None, notes


def prune_checkpoints(run_dir: Path, keep: int) -> list[Path]:
    """Delete all but the newest ``keep`` checkpoints of ``run_dir`` (``keep`` 0: none); returns what was deleted."""
    if keep <= 0:
        return []
    removed = []
    for _, path in run_checkpoints(run_dir)[:-keep]:
        path.unlink(missing_ok=True)
        removed.append(path)
    return removed
