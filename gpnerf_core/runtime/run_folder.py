"""A run folder one run holds at a time: a lock file naming the holder, and no silent mixing of two runs.

``claim`` creates the folder, takes ``.gpnerf.lock`` (pid, host, start time, command) with an exclusive create,
and refuses a folder that already holds a run unless the run resumes or ``overwrite=true`` replaces it. A lock
left by a process that no longer runs on this host is taken over; one from another host is not (its process
cannot be checked from here), and the error says which file to delete.

A command that fails removes only what it created itself: the run files it wrote before the run's first checkpoint
(``RunFolder`` leaving its ``with`` block on an error) and the folders it made that are left empty
(``remove_made_folders``). A refusal removes nothing it did not create in that same call.
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
from gpnerf_core.runtime.signals import interrupted_by

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
    "render.json", "trajectory.mp4", "trajectory.gif", "legend.png",  # render's
    "export.json", "points.ply", "points_labels.ply", "gaussians.ply",  # export's
    "labels.json",  # label's
)
RUN_FOLDERS = ("checkpoints", "images", "tensorboard", "frames", "labels")
"""What a run (``run``, ``eval``, ``finetune``, ``render``, ``export``, ``label``) writes; ``overwrite=true`` deletes
exactly these."""

_STARTED = time.time()
"""When this process imported the module: a folder made after it, still empty, was made for this command."""
_MADE_FOLDERS: list[Path] = []
"""Folders this process created for its runs (``make_folder``, ``adopt_new_folder``), outermost first."""


def make_folder(path: Path) -> None:
    """``mkdir -p path``, remembering every level it creates: the only folders a failed command removes."""
    path = Path(path).absolute()
    missing = [level for level in (path, *path.parents) if not level.exists()]
    path.mkdir(parents=True, exist_ok=True)
    _MADE_FOLDERS.extend(level for level in reversed(missing) if level not in _MADE_FOLDERS)


def adopt_new_folder(path: Path) -> None:
    """Count ``path`` as made by this command when it is empty and was made after this process started (the run
    folder Hydra creates just before a job starts)."""
    path = Path(path).absolute()
    try:
        if path in _MADE_FOLDERS or any(path.iterdir()) or path.stat().st_mtime < _STARTED:
            return
    except OSError:
        return
    _MADE_FOLDERS.append(path)


def made_by_this_command(path: Path) -> bool:
    """True when this process created ``path`` (``make_folder``, ``adopt_new_folder``)."""
    return Path(path).absolute() in _MADE_FOLDERS


def remove_made_folders(path: Path) -> None:
    """Remove ``path``, and the parents made with it, if this command made them and they are empty; a folder it did
    not make, or one holding anything, stays as it is."""
    level = Path(path).absolute()
    while level in _MADE_FOLDERS:
        try:
            level.rmdir()
        except OSError:  # not empty (or gone): what is in it is not this command's to remove
            return
        _MADE_FOLDERS.remove(level)
        level = level.parent


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
        self._found: dict[str, tuple[int, int, int]] = {}
        """The run files in the folder when it was claimed (relative path -> identity)."""
        self._found_folders: set[Path] = set()
        """The folders under ``RUN_FOLDERS`` (and those) there when it was claimed."""

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
            make_folder(self.path)
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
            self._found = _run_file_identities(self.path)
            self._found_folders = _run_folders(self.path)
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

    def __exit__(self, exc_type: object, exc: BaseException | None, traceback: object) -> None:
        """Release the lock; on an error (not an interruption, whose files stay) first ``discard_written``."""
        try:
            if exc is not None and self._held and interrupted_by(exc) is None:
                self.discard_written()
        finally:
            self.release()

    def discard_written(self) -> list[Path]:
        """Remove the run files (``RUN_FILES``, files under ``images``/``tensorboard``) this command wrote, unless the
        folder holds a checkpoint (a run that can resume keeps everything). Files that were there when the folder
        was claimed, and files no run writes (a diagnostic an error names), stay. Returns what was removed."""
        if any((self.path / "checkpoints").glob("step_*.pt")):
            return []
        removed = []
        for relative, identity in _run_file_identities(self.path).items():
            if self._found.get(relative) != identity:
                (self.path / relative).unlink(missing_ok=True)
                removed.append(self.path / relative)
        for folder in sorted(_run_folders(self.path) - self._found_folders, reverse=True):  # deepest first
            try:
                folder.rmdir()
            except OSError:  # not empty: it holds what this command did not write
                pass
        return removed

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


def _run_file_identities(folder: Path) -> dict[str, tuple[int, int, int]]:
    """``relative path -> (inode, mtime ns, size)`` of the run files ``discard_written`` may remove: ``RUN_FILES``
    and the files under ``images`` and ``tensorboard`` (never checkpoints)."""
    paths = [folder / name for name in RUN_FILES]
    for name in ("images", "tensorboard"):
        if (folder / name).is_dir() and not (folder / name).is_symlink():
            paths += [p for p in (folder / name).rglob("*")]
    found = {}
    for path in paths:
        try:
            stat = path.lstat()
        except OSError:
            continue
        if path.is_file() and not path.is_symlink():
            found[str(path.relative_to(folder))] = (stat.st_ino, stat.st_mtime_ns, stat.st_size)
    return found


def _run_folders(folder: Path) -> set[Path]:
    """``RUN_FOLDERS`` in ``folder`` and every folder under them."""
    found = set()
    for name in RUN_FOLDERS:
        root = folder / name
        if root.is_dir() and not root.is_symlink():
            found |= {root, *(p for p in root.rglob("*") if p.is_dir() and not p.is_symlink())}
    return found
