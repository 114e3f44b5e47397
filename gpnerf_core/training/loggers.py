"""Scalar loggers: training scalars and evaluation metrics where users look (CSV, TensorBoard).

Both write under the run folder, on rank 0 only, with the same tags: ``train/loss``, ``train/lr/head``,
``train/rays_per_second``, ``eval/<split>/miou/image_mean_present``, ... (``training_curves.json`` keeps the
per-step entries as well).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Mapping, Protocol

from gpnerf_core.errors import ConfigError
from gpnerf_core.runtime.io import atomic_open

KNOWN_LOGGERS = ("csv", "tensorboard")


class ScalarLogger(Protocol):
    def log(self, step: int, scalars: Mapping[str, float]) -> None:
        """Record ``{tag: value}`` at ``step``."""

    def close(self) -> None:
        """Flush and release files."""


class CsvLogger:
    """``scalars.csv`` with columns ``step, tag, value``, one row per scalar, appended and flushed per call.

    Args:
        path: the CSV file.
        resume_step: rows after this step (left by a run that went further than the checkpoint it resumes
            from) are dropped first; None starts a new file.
    """

    COLUMNS = ("step", "tag", "value")

    def __init__(self, path: Path, resume_step: int | None = None) -> None:
        self.path = path
        rows = []
        if resume_step is not None and path.is_file():
            with path.open(newline="") as handle:
                rows = [row for row in csv.DictReader(handle) if int(row["step"]) <= resume_step]
        with atomic_open(path, "w") as handle:
            writer = csv.DictWriter(handle, self.COLUMNS, lineterminator="\n")
            writer.writeheader()
            writer.writerows(rows)
        self._handle = path.open("a", newline="")
        self._writer = csv.writer(self._handle, lineterminator="\n")

    def log(self, step: int, scalars: Mapping[str, float]) -> None:
        self._writer.writerows((step, tag, repr(float(value))) for tag, value in scalars.items())
        self._handle.flush()

    def close(self) -> None:
        self._handle.close()


class TensorBoardLogger:
    """TensorBoard event files in ``<run folder>/tensorboard`` (``torch.utils.tensorboard``).

    Args:
        folder: the event-file folder.
        resume_step: events after this step are purged from the view (TensorBoard's ``purge_step``).
    """

    def __init__(self, folder: Path, resume_step: int | None = None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        purge = None if resume_step is None else resume_step + 1
        self._writer = SummaryWriter(log_dir=str(folder), purge_step=purge)

    def log(self, step: int, scalars: Mapping[str, float]) -> None:
        for tag, value in scalars.items():
            self._writer.add_scalar(tag, float(value), step)
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()


def make_loggers(names: list[str], run_dir: Path, resume_step: int | None = None) -> list[ScalarLogger]:
    """The loggers ``train.loggers`` names, writing under ``run_dir``."""
    check_loggers(names)
    loggers: list[ScalarLogger] = []
    if "csv" in names:
        loggers.append(CsvLogger(run_dir / "scalars.csv", resume_step))
    if "tensorboard" in names:
        loggers.append(TensorBoardLogger(run_dir / "tensorboard", resume_step))
    return loggers


def check_loggers(names: list[str]) -> None:
    """Refuse unknown logger names and a missing tensorboard package before any work is done."""
    unknown = [name for name in names if name not in KNOWN_LOGGERS]
    if unknown:
        raise ConfigError(f"train.loggers contains {unknown[0]!r}; known loggers: {', '.join(KNOWN_LOGGERS)}")
    if "tensorboard" in names:
        import importlib.util

        if importlib.util.find_spec("tensorboard") is None:
            raise ConfigError(
                "train.loggers contains 'tensorboard' but the tensorboard package is not installed: "
                "pip install 'gpnerf-core[tensorboard]' (or drop it from train.loggers)"
            )
