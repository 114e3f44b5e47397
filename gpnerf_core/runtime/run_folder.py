"""A run folder one run holds at a time: a lock file naming the holder, and no silent mixing of two runs.

``claim`` creates the folder, takes ``.gpnerf.lock`` (pid, host, start time, command) with an exclusive create,
and refuses a folder that already holds a run unless the run resumes or ``overwrite=true`` replaces it. A lock
left by a process that no longer runs on this host is taken over; one from another host is not (its process
cannot be checked from here), and the error says which file to delete.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import sys
import time
from pathlib import Path
from typing import Sequence

from gpnerf_core.errors import GpnerfError

LOCK_NAME = ".gpnerf.lock"

SETUP_FILES = ("config.yaml", "config.sha256", "overrides.yaml", "plugins.json")
"""Written before training starts: a folder holding only these is a run that never trained, and is reused."""

RUN_FILES = (
    *SETUP_FILES,
    "metrics.json",
    "training_curves.json",
    "training_curves.png",
    "scalars.csv",
    "bench.json",
    "finetune_curve.json",
)
RUN_FOLDERS = ("checkpoints", "images", "tensorboard")
"""What a run writes; ``overwrite=true`` deletes exactly these."""


class RunFolderError(GpnerfError):
    """The run folder cannot be used: held by another run, holding a finished run, or not writable."""


class RunFolder:
    """The folder a run writes, held through a lock file while the run lives.

    Args:
        path: the folder (created by ``claim``).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.lock_path = self.path / LOCK_NAME
        self._held = False

    def claim(self, *, resuming: bool, overwrite: bool, inputs: Sequence[Path] = ()) -> list[str]:
        """Create and lock the folder; returns notes to print (a stale lock taken over, a run replaced).

        Args:
            inputs: files the command reads (its checkpoint, the one it resumes from): ``overwrite`` is refused when it
                would delete one of them.

        Raises:
            RunFolderError: another live run holds it; it holds a run and neither ``resuming`` nor ``overwrite``;
                it holds files that are not a run's (``overwrite`` never deletes those); it cannot be created.
        """
        notes = []
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunFolderError(
                f"run folder {self.path} cannot be created ({exc.strerror or exc}); choose a writable out_dir"
            ) from None
        stale = self._take_lock()
        if stale:
            notes.append(stale)
        try:
            others = sorted(p.name for p in self.path.iterdir() if p.name not in (LOCK_NAME, *SETUP_FILES))
            if others and not resuming:
                foreign = [name for name in others if name not in RUN_FILES + RUN_FOLDERS]
                if not overwrite:
                    has_checkpoint = any((self.path / "checkpoints").glob("step_*.pt"))
                    advice = ("resume its run with train.resume=auto (or =<checkpoint>)" if has_checkpoint
                              else "it holds no checkpoint to resume from")
                    raise RunFolderError(
                        f"run folder {self.path} is not empty ({', '.join(others[:4])}"
                        f"{', ...' if len(others) > 4 else ''}): {advice}; replace it with overwrite=true, or "
                        "choose another out_dir"
                    )
                if foreign:
                    raise RunFolderError(
                        f"run folder {self.path} holds files no run writes (first: {foreign[0]!r}); "
                        "overwrite=true only replaces a previous run's files: choose another out_dir"
                    )
                read = next((p for p in inputs if self._would_remove(p)), None)
                if read is not None:
                    raise RunFolderError(
                        f"overwrite=true would delete {read}, which this command reads; write to another out_dir"
                    )
                self._remove_run_files()
                notes.append(f"overwrite=true: removed the previous run's files from {self.path}")
        except BaseException:
            self.release()
            raise
        return notes

    def release(self) -> None:
        """Remove the lock if this process holds it."""
        if self._held:
            self._held = False
            try:
                self.lock_path.unlink()
            except FileNotFoundError:
                pass

    def __enter__(self) -> "RunFolder":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.release()

    def _take_lock(self) -> str | None:
        holder = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": time.strftime("%Y-%m-%d %H:%M:%S"),
            "command": " ".join(sys.argv),
        }
        note = None
        for _ in range(2):
            try:
                fd = os.open(self.lock_path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                current = self._read_lock()
                if not self._holder_is_dead(current):
                    raise RunFolderError(
                        f"run folder {self.path} is held by a running run (pid {current.get('pid')} on "
                        f"{current.get('host')}, since {current.get('started')}); choose another out_dir, or "
                        f"if that run is gone, delete {self.lock_path}"
                    ) from None
                note = f"took over the lock of a run that no longer runs (pid {current.get('pid')})"
                self.lock_path.unlink(missing_ok=True)
                continue
            except OSError as exc:
                raise RunFolderError(
                    f"run folder {self.path} is not writable ({exc.strerror or exc}); choose a writable out_dir"
                ) from None
            with os.fdopen(fd, "w") as handle:
                json.dump(holder, handle)
            self._held = True
            return note
        raise RunFolderError(f"run folder {self.path}: could not take {self.lock_path} (another run took it first)")

    def _read_lock(self) -> dict:
        try:
            return json.loads(self.lock_path.read_text())
        except (OSError, ValueError):
            return {}

    @staticmethod
    def _holder_is_dead(holder: dict) -> bool:
        """True only when the holder ran on this host and its pid is gone."""
        if holder.get("host") != socket.gethostname() or not isinstance(holder.get("pid"), int):
            return False
        try:
            os.kill(holder["pid"], 0)
        except ProcessLookupError:
            return True
        except PermissionError:
            return False
        return False

    def _would_remove(self, path: Path) -> bool:
        """True when ``path`` is (or lies inside) one of the run files ``overwrite`` deletes."""
        try:
            resolved = Path(path).resolve()
        except OSError:
            return False
        removed = [(self.path / name).resolve() for name in (*RUN_FILES, *RUN_FOLDERS)]
        return any(resolved == target or target in resolved.parents for target in removed)

    def _remove_run_files(self) -> None:
        for name in RUN_FILES:
            (self.path / name).unlink(missing_ok=True)
        for name in RUN_FOLDERS:
            shutil.rmtree(self.path / name, ignore_errors=True)


LEFTOVERS = ("scalars.csv", "training_curves.json", "training_curves.png", "tensorboard", "images")
"""What a run that failed before its first checkpoint may have written besides the setup files."""


def remove_untrained_run(path: Path) -> None:
    """Delete what a run that failed before its first checkpoint left in ``path`` (the setup files, the logs opened
    before training, the folder itself once empty). A folder holding anything else (a checkpoint, metrics, files no
    run writes) or locked by a live run is left untouched."""
    path = Path(path)
    try:
        entries = list(path.iterdir())
    except OSError:
        return
    if (path / LOCK_NAME).exists() or any(entry.name not in (*SETUP_FILES, *LEFTOVERS) for entry in entries):
        return
    for entry in entries:
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
    try:
        path.rmdir()
    except OSError:
        pass
