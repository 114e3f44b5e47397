"""A job's run folder and what it records there: where the folder is (``run_dir``), claiming it (``claim_run_folder``,
the first write of a command) and the record of what the run is made from (``run_record``, ``task_overrides``)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from gpnerf_core.config.overrides import is_search_path
from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.model.checkpoint import RunRecord
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.runtime.io import atomic_write_json, atomic_write_text
from gpnerf_core.runtime.run_folder import RunFolder, RunFolderError

CLAIMED_FOLDERS: set[Path] = set()
"""Run folders this process claimed (``claim_run_folder``): a failed sweep job may write its record there."""


def hydra_config() -> Any:
    """Hydra's runtime config of this job, or None outside a Hydra job (a test, a notebook)."""
    from hydra.core.hydra_config import HydraConfig

    return HydraConfig.get() if HydraConfig.initialized() else None


def run_dir(cfg: DictConfig) -> Path:
    """The job's run folder: ``out_dir`` when set, else Hydra's output directory."""
    if cfg.out_dir:
        return Path(cfg.out_dir)
    hydra = hydra_config()
    if hydra is None:
        raise ConfigError("out_dir is empty and no Hydra run directory exists; set out_dir=<folder>")
    return Path(hydra.runtime.output_dir)


def task_overrides() -> tuple[str, ...]:
    """The Hydra overrides of this job as typed (``+head=unet``, ``train.steps=10``, ...), and the search path if one
    was given (``eval``, ``finetune`` and resuming compose the checkpoint's overrides again and need it)."""
    hydra = hydra_config()
    if hydra is None:
        return ()
    return (*[o for o in hydra.overrides.hydra if is_search_path(o)], *hydra.overrides.task)


def shared_run_dir(cfg: DictConfig, dist: Distributed) -> Path:
    """The run folder, as rank 0 names it (``run_dir``), on every rank; nothing is created."""
    return Path(dist.broadcast_object(str(run_dir(cfg)) if dist.is_main else None))


def claim_run_folder(
    cfg: DictConfig,
    dist: Distributed,
    *,
    resuming: bool,
    replace_leftovers: bool = False,
    record: RunRecord | None = None,
) -> tuple[RunFolder, RunRecord]:
    """Rank 0 claims (locks) the run folder and writes what the run is made from; every rank gets the same folder.

    Call it once every check that can refuse the command has passed: it is the first write into the folder.

    Returns the claimed folder (a context manager that releases the lock and, on an error, removes the run files this
    command wrote before a checkpoint) and the run's record (config YAML, its hash, overrides, components with
    providers and versions; ``record``, or ``run_record(cfg)``). A refusal (a live run holds the folder; a finished
    run is there and neither resuming nor ``overwrite=true``) is raised on every rank as one ``RunFolderError``.
    """
    folder_path = shared_run_dir(cfg, dist)
    folder = RunFolder(folder_path)
    outcome: tuple[str, Any] = ("ok", [])
    if dist.is_main:
        try:
            overwrite = bool(cfg.overwrite) or replace_leftovers
            outcome = ("ok", folder.claim(resuming=resuming, overwrite=overwrite, inputs=command_inputs(cfg)))
        except GpnerfError as exc:
            outcome = ("error", str(exc))
    outcome = dist.broadcast_object(outcome)
    if outcome[0] == "error":
        raise RunFolderError(outcome[1])
    record = record or run_record(cfg)
    if dist.is_main:
        CLAIMED_FOLDERS.add(folder_path.absolute())
        for note in outcome[1]:
            print(f"note: {note}", file=sys.stderr)
        try:
            _write_run_files(folder_path, record)
        except BaseException as exc:
            folder.__exit__(type(exc), exc, exc.__traceback__)
            raise
    return folder, record


def command_inputs(cfg: DictConfig) -> list[Path]:
    """Files the job reads that a run folder may hold: ``checkpoint``, ``train.resume``, ``model.init``."""
    values = [cfg.get("checkpoint"), OmegaConf.select(cfg, "train.resume"), OmegaConf.select(cfg, "model.init")]
    return [Path(str(v)) for v in values if v and str(v) != "auto"]


def run_record(cfg: DictConfig, model_sections: tuple[str, ...] | None = None) -> RunRecord:
    """The run's config (resolved), overrides and the components it uses with their providers and versions, and the
    config sections that define its model (``Components.model_sections``; None: not known)."""
    components = {
        kind: {"name": entry.spec.name, "provider": entry.provider, "version": entry.version,
               "distribution": entry.distribution}
        for kind, entry in components_of(cfg).items()
    }
    return RunRecord(
        config_yaml=OmegaConf.to_yaml(cfg, resolve=True), overrides=task_overrides(), components=components,
        model_sections=model_sections or None,
    )


def components_of(cfg: DictConfig) -> dict[str, Any]:
    """``kind -> RegisteredComponent`` of the components ``cfg`` selects."""
    from gpnerf_core.registry.components import get_registry
    from gpnerf_core.registry.kinds import KINDS, section

    registry = get_registry()
    found = {}
    for kind in KINDS:
        node = section(cfg, kind)
        if node is not None and "name" in node and str(node.name) in registry.components[kind]:
            found[kind] = registry.components[kind][str(node.name)]
    return found


def _write_run_files(folder: Path, record: RunRecord) -> None:
    from gpnerf_core.registry.components import get_registry

    registry = get_registry()
    atomic_write_text(folder / "config.yaml", record.config_yaml)
    atomic_write_text(folder / "config.sha256", record.config_sha256 + "\n")
    atomic_write_text(folder / "overrides.yaml", OmegaConf.to_yaml(list(record.overrides)))
    atomic_write_json(
        folder / "plugins.json",
        {
            "used": record.components,
            "components": [
                {"kind": e.kind, "name": e.spec.name, "provider": e.provider, "version": e.version}
                for entries in registry.components.values()
                for e in entries.values()
            ],
            "disabled": registry.disabled,
            "problems": [
                {"plugin": p.plugin.name, "distribution": p.plugin.distribution, "version": p.plugin.version,
                 "component": p.component, "reason": p.reason}
                for p in registry.problems
            ],
        },
    )
