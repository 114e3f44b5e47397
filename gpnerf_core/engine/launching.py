"""How every Hydra command of ``python -m gpnerf_core`` starts, before Hydra creates anything.

The lifecycle a Hydra command (``run``, ``eval``, ``finetune``, ``render``, ``view``, ``export``, ``label``) goes
through, in this order:

1. ``launch(task, argv, prog)`` (or ``launch_from_checkpoint``, which reads ``checkpoint=`` once): refuses an unknown
   component name, composes and validates the config (``precheck``; a checkpoint's settings restored first) and only
   then hands the arguments to Hydra, which creates the run folder. Guarantee: a bad override or value is one line and
   exit code 2, and nothing is written. Each job gets what the launcher did (``Handover``): the config validated, the
   checkpoint read.
2. ``guarding.job`` around the task: the torchrun process group, and one line plus an exit code for every error caused
   by input or environment (``engine.guarding``; a ``-m`` sweep's failed jobs: ``engine.sweeps``).
3. ``setup.start(cfg, validated=...)`` inside the task (``opening.open_trained`` for a trained model): validates a
   config that was not prechecked (a sweep's jobs), refuses a fixed ``out_dir`` shared by a sweep's jobs, sets the
   threads and the seed (which fixes the model's initialisation) and chooses the device.
4. ``resuming.plan_resume(cfg, dist)`` (``run``, ``finetune``): the checkpoint to resume from, and every refusal of it.
5. ``runs.claim_run_folder(cfg, dist, resuming=...)``, the first write into the run folder, once nothing can refuse the
   command any more.

Commands that are not Hydra jobs (``report``, ``stress``, ``size``, ``bench``) parse their own arguments
(``gpnerf_core.config.arguments.ArgumentParser``) and use the same error convention: raise a ``GpnerfError``;
``cli.main`` prints it as one line and exits 2.
"""

from __future__ import annotations

import functools
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from omegaconf import DictConfig

from gpnerf_core.config.overrides import is_search_path, merge_overrides, quoted_for_hydra
from gpnerf_core.engine.opening import check_family_choice, restore_trained_settings
from gpnerf_core.engine.setup import check_component_choices, check_config, compose_overrides
from gpnerf_core.engine.sweeps import ERROR_FILE, FAILED_SWEEP_JOBS
from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.model.checkpoint import check_recorded_components
from gpnerf_core.model.trained import TrainedModel, load_trained
from gpnerf_core.runtime.run_folder import RunFolderError, make_folder


@dataclass(frozen=True)
class Handover:
    """What the launcher did before Hydra, handed to each job so that it does not do it again.

    Attributes:
        validated: the job's config passed validation before Hydra (``precheck``); False for the jobs of a ``-m``
            sweep and of a launch with Hydra's own flags, which each validate their config once themselves.
        trained: the checkpoint ``launch_from_checkpoint`` read (None: none). A job pickled into another process
            (submitit) gets None and reads the file there: the tensors never travel in the pickle.
    """

    validated: bool = False
    trained: TrainedModel | None = None

    def __reduce__(self) -> tuple[Any, ...]:
        return (Handover, (self.validated, None))


def launch(task: Callable[[DictConfig, Handover], Any], argv: list[str], prog: str, *,
           trained: TrainedModel | None = None, command: str = "") -> int:
    """Run ``task(cfg, handover)`` as a Hydra job (or a ``-m`` sweep of them) on ``argv``; the command's exit code.

    Args:
        trained: the checkpoint ``argv`` was composed from (``launch_from_checkpoint``): its settings are restored
            before the config is validated, and each job gets this read. command: its name, for the errors.

    Guarantees: an unknown component name, an override Hydra cannot compose and a value the schema refuses are each
    one ``GpnerfError`` raised before Hydra creates any folder. Returns 2 when some jobs of a sweep failed.
    """
    import hydra

    from gpnerf_core.config.compose import config_dir, register_schema
    from gpnerf_core.registry.components import get_registry

    argv = [quoted_for_hydra(argument) for argument in argv]
    check_component_choices(argv, get_registry())
    register_schema()
    handover = Handover(precheck(argv, trained, command), trained)
    sys.argv = [prog, *argv]
    FAILED_SWEEP_JOBS.clear()
    hydra.main(version_base="1.3", config_path=config_dir(), config_name="config")(_handing(task, handover))()
    failed = list(dict.fromkeys(FAILED_SWEEP_JOBS))
    if failed:
        print(f"error: {len(failed)} job(s) of the sweep failed ({ERROR_FILE} in each): {', '.join(failed)}",
              file=sys.stderr)
        return 2
    return 0


def _handing(task: Callable[[DictConfig, Handover], Any], handover: Handover) -> Callable[[DictConfig], Any]:
    """``task`` as the Hydra task ``f(cfg)``, each job handed ``handover``."""

    @functools.wraps(task)
    def hydra_task(cfg: DictConfig) -> Any:
        return task(cfg, handover)

    return hydra_task


def launch_from_checkpoint(task: Callable[[DictConfig, Handover], Any], argv: list[str], command: str) -> int:
    """``launch`` with the config of ``checkpoint=<path>`` in ``argv``: its overrides, then the command's (which win),
    its model settings restored where the command did not set them (``opening.restore_trained_settings``).

    The checkpoint is read here, once: each job gets this read (``Handover.trained``)."""
    if "--help" in argv or "-h" in argv:  # Hydra's help (config groups and options): no checkpoint needed
        return launch(task, argv, f"gpnerf_core {command}")
    given = [a for a in argv if a.startswith("checkpoint=")]
    if not given:
        raise GpnerfError(f"{command} needs checkpoint=<path to a .pt file written by run>")
    trained = load_trained(given[-1].split("=", 1)[1])
    check_recorded_components(trained.state, trained.path)
    check_family_choice(trained, argv, command)
    return launch(task, merge_overrides(trained.overrides, argv), f"gpnerf_core {command}", trained=trained,
                  command=command)


def precheck(argv: list[str], trained: TrainedModel | None = None, command: str = "") -> bool:
    """Compose and validate the config before Hydra starts (and creates the run folder), so a bad override or value
    is one line and exit code 2; True when it did. ``trained``: the checkpoint ``argv`` was composed from, whose model
    settings are restored first (``opening.restore_trained_settings``), as the job will. Sweeps (``-m``), Hydra's own
    flags and ``${hydra:...}`` values (which only resolve inside a job) are left to Hydra: False, and every job
    validates its own config."""
    if any(argument.startswith("-") or "${hydra:" in argument for argument in argv):
        return False
    overrides = [a for a in argv if not a.lstrip("+~").startswith(("hydra.", "hydra/")) or is_search_path(a)]
    cfg = compose_overrides(overrides)
    if trained is not None:
        restore_trained_settings(cfg, trained, overrides, command)
    check_config(cfg)
    if cfg.out_dir:
        check_writable_folder(Path(cfg.out_dir))
    else:
        check_default_output_root(Path("outputs"))
    return True


def check_default_output_root(root: Path) -> None:
    """Without ``out_dir`` Hydra makes the run folder under ``root`` in the working folder, with a traceback where it
    cannot: try it first (a folder made and removed at once), as one line."""
    import tempfile

    parent = root if root.is_dir() else root.parent
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".gpnerf-write-test-", dir=parent))
    except OSError as exc:
        raise ConfigError(
            f"out_dir is not set and runs go to {root.resolve()}, where no folder can be made ({exc.strerror or exc}); "
            "set out_dir=<a writable folder>"
        ) from None


def check_writable_folder(path: Path) -> None:
    """Create ``path`` (Hydra would, with a traceback on failure): one line naming it when that is impossible. The
    folders made are remembered: a refused or failed command removes them again (``remove_made_folders``)."""
    try:
        make_folder(path)
    except OSError as exc:
        raise RunFolderError(
            f"out_dir={path} cannot be created ({exc.strerror or exc}); choose a writable out_dir"
        ) from None
