"""A ``-m`` sweep's failed jobs: each writes ``error.json`` into its folder and the others go on
(``record_sweep_failure``); after the sweep they are collected (``SweepFailures``, a Hydra callback) into
``FAILED_SWEEP_JOBS``, and the command exits 2 (``launching.launch``)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from gpnerf_core.engine.runs import CLAIMED_FOLDERS, hydra_config, run_dir, task_overrides
from gpnerf_core.errors import GpnerfError
from gpnerf_core.runtime.io import atomic_write_json, atomic_write_text
from gpnerf_core.runtime.run_folder import RunFolderError, made_by_this_command, make_folder

FAILED_SWEEP_JOBS: list[str] = []
"""Run folders of the jobs of this process's ``-m`` sweep that failed (the command exits 2 after the sweep)."""
ERROR_FILE = "error.json"
"""A failed sweep job's record in its folder: ``{"error": <the line>, "overrides": [...]}`` (``report`` shows it)."""


class SweepFailures(Callback):
    """Hydra callback (``hydra.callbacks`` in ``conf/config.yaml``): after a ``-m`` sweep, the jobs that failed are
    found by the ``error.json`` they wrote under the sweep folder during this sweep, whatever launcher ran them (in
    this process, or pickled into other processes by submitit), and added to ``FAILED_SWEEP_JOBS``."""

    def __init__(self) -> None:
        self.started = time.time()

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self.started = time.time()

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        folder = Path(str(config.hydra.sweep.dir))
        for marker in sorted(folder.rglob(ERROR_FILE)) if folder.is_dir() else []:
            if marker.stat().st_mtime < self.started - 1:
                continue
            try:
                failed = str(json.loads(marker.read_text()).get("run_folder") or marker.parent)
            except (OSError, ValueError, AttributeError):
                failed = str(marker.parent)
            failed = str(Path(failed).absolute())  # the job's own entry is absolute: one job is listed once
            if failed not in FAILED_SWEEP_JOBS:
                FAILED_SWEEP_JOBS.append(failed)


def in_sweep() -> bool:
    """True inside a job of a ``-m`` sweep."""
    from hydra.types import RunMode

    hydra = hydra_config()
    return hydra is not None and hydra.mode == RunMode.MULTIRUN


def refuse_shared_out_dir(cfg: DictConfig) -> None:
    """Under ``-m`` every job would write one fixed ``out_dir``: refuse unless it depends on the job."""
    if not in_sweep() or not cfg.out_dir:
        return
    raw = OmegaConf.to_container(cfg, resolve=False).get("out_dir")  # the interpolation as typed, before resolving
    if "${" not in str(raw):
        raise RunFolderError(
            f"out_dir={cfg.out_dir} with -m: every job of the sweep would write that one folder; leave out_dir "
            "unset (jobs go under hydra.sweep.dir) or make it depend on the job, e.g. 'out_dir=runs/${hydra:job.num}'"
        )


def record_sweep_failure(cfg: DictConfig, message: str, *, refused_folder: bool = False) -> bool:
    """Record a failed job of a sweep: ``error.json`` (the error and the job's overrides) into its run folder, and
    into Hydra's folder of the job when that is another; the job counts once in ``FAILED_SWEEP_JOBS``. False when
    writing failed.

    The run folder gets the record (and the job's ``config.yaml``, if it has none) only when the job may write
    there: not when it was refused that folder (``refused_folder``: shared by the sweep's jobs, held by a run,
    not empty), and only a folder this command made or claimed (a finished run's folder is not marked failed).
    """
    record = {"error": message, "overrides": list(task_overrides())}
    hydra = hydra_config()
    job_dir = Path(hydra.runtime.output_dir) if hydra is not None else None
    try:
        folder = run_dir(cfg)
    except GpnerfError:
        folder = None
    written = None
    try:
        if folder is not None and not refused_folder and _may_record_into(folder):
            make_folder(folder)
            atomic_write_json(folder / ERROR_FILE, record)
            if not (folder / "config.yaml").exists():
                atomic_write_text(folder / "config.yaml", OmegaConf.to_yaml(cfg, resolve=False))
            written = folder
        if job_dir is not None and (folder is None or job_dir.resolve() != folder.resolve()):
            # Hydra's folder of this job, where SweepFailures looks: it names the run folder holding the record
            atomic_write_json(job_dir / ERROR_FILE, record | ({"run_folder": str(written)} if written else {}))
            written = written or job_dir
    except (GpnerfError, OSError, ValueError):
        return False
    FAILED_SWEEP_JOBS.append(str(Path(written).absolute()) if written
                             else f"{folder or job_dir} (refused: no {ERROR_FILE} written)")
    return True


def _may_record_into(folder: Path) -> bool:
    """A failed job writes its record only into a folder that does not exist yet, or that this command made or
    claimed."""
    return not folder.exists() or made_by_this_command(folder) or folder.absolute() in CLAIMED_FOLDERS
