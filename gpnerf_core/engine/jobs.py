"""The lifecycle every command of ``python -m gpnerf_core`` shares, as public functions.

A Hydra command (``run``, ``eval``, ``finetune``, ``render``) goes through these steps, in this order:

1. ``launch(task, argv, prog)`` (or ``launch_from_checkpoint``): refuses an unknown component name, composes and
   validates the config (``precheck``) and only then hands the arguments to Hydra, which creates the run folder.
   Guarantee: a bad override or value is one line and exit code 2, and nothing is written.
2. ``@job`` around the task: joins the torchrun process group (if any) and turns every error caused by input or
   environment into one line on stderr and an exit code, never a traceback (``GPNERF_DEBUG=1`` re-raises).
   An exception raised in a component's own code (a plugin's bug) is one line naming the component, its plugin and
   distribution, exit code 1. In a ``-m`` sweep a failing job writes ``error.json`` into its own folder (never into
   a folder it was refused for) and the others go on; the command exits 2 after the sweep (``FAILED_SWEEP_JOBS``,
   one entry per failed job). A failed job removes only what it created: the run files it wrote before a
   checkpoint, and the folders it made; a refusal removes nothing else.
3. ``start(cfg)`` inside the task: validates again (a sweep's jobs were not prechecked), refuses a fixed ``out_dir``
   shared by a sweep's jobs, sets the thread count and the seed (which fixes the model's initialisation).
4. ``plan_resume(cfg, dist)`` (``run``): turns ``train.resume=auto`` into the newest intact checkpoint of ``out_dir`` (or a
   fresh start) and refuses a resume the checkpoint cannot honour (another seed, fewer steps than it reached,
   another model or loss); ``run`` then builds its trainer, whose own resume checks refuse before step 5 too.
5. ``claim_run_folder(cfg, dist, resuming=...)``, the first write into the run folder, once nothing can refuse the
   command any more: rank 0 locks the run folder (refusing a live one, and a finished one
   unless resuming or ``overwrite=true``) and writes what the run is made from (``config.yaml``, its hash,
   ``overrides.yaml``, ``plugins.json``); every other rank learns the folder from rank 0 and writes nothing.

Commands that are not Hydra jobs (``report``, ``stress``, ``size``, ``bench``) parse their own arguments
(``gpnerf_core.config.arguments.ArgumentParser``) and use the same error convention: raise a ``GpnerfError``; ``cli.main`` prints it as one line and exits 2.
"""

from __future__ import annotations

import json
import os
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch
import yaml
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict

from gpnerf_core.data.dataset import FittedScenes
from gpnerf_core.model.build import build_components
from gpnerf_core.runtime.distributed import Distributed, init_distributed
from gpnerf_core.errors import ConfigError, DataError, GpnerfError
from gpnerf_core.runtime.io import atomic_write_json, atomic_write_text
from gpnerf_core.config.overrides import (
    RUN_SPECIFIC_KEYS,
    is_search_path,
    merge_overrides,
    override_key,
    quoted_for_hydra,
)
from gpnerf_core.runtime.signals import Terminated, interrupted_by, interruption
from gpnerf_core.runtime.run_folder import (
    RunFolder,
    RunFolderError,
    adopt_new_folder,
    made_by_this_command,
    make_folder,
    remove_made_folders,
)
from gpnerf_core.model.checkpoint import (
    RunRecord, check_recorded_components, check_resume_config, format_differences, model_differences,
)
from gpnerf_core.model.trained import TrainedModel, checked_checkpoint_path, load_trained, restore_model_settings
from gpnerf_core.model.weights import load_weights
from gpnerf_core.training.interrupt import TrainingInterrupted
from gpnerf_core.training.resume import newest_intact_checkpoint
from gpnerf_core.engine.setup import check_component_choices, check_config, compose_checked, setup_process
from gpnerf_core.engine.validation import check_data

FAILED_SWEEP_JOBS: list[str] = []
"""Run folders of the jobs of this process's ``-m`` sweep that failed (the command exits 2 after the sweep)."""
ERROR_FILE = "error.json"
"""A failed sweep job's record in its folder: ``{"error": <the line>, "overrides": [...]}`` (``report`` shows it)."""


# -- 1. before Hydra: refuse bad input while nothing is written -------------------------------------------------


def launch(task: Callable[[DictConfig], Any], argv: list[str], prog: str) -> int:
    """Run ``task`` as a Hydra job (or a ``-m`` sweep of them) on ``argv``; the command's exit code.

    Guarantees: an unknown component name, an override Hydra cannot compose and a value the schema refuses are each
    one ``GpnerfError`` raised before Hydra creates any folder. Returns 2 when some jobs of a sweep failed.
    """
    import hydra

    from gpnerf_core.config.compose import config_dir, register_schema
    from gpnerf_core.registry.components import get_registry

    argv = [quoted_for_hydra(argument) for argument in argv]
    check_component_choices(argv, get_registry())
    register_schema()
    precheck(argv)
    sys.argv = [prog, *argv]
    FAILED_SWEEP_JOBS.clear()
    hydra.main(version_base="1.3", config_path=config_dir(), config_name="config")(task)()
    failed = list(dict.fromkeys(FAILED_SWEEP_JOBS))
    if failed:
        print(f"error: {len(failed)} job(s) of the sweep failed ({ERROR_FILE} in each): {', '.join(failed)}",
              file=sys.stderr)
        return 2
    return 0


def launch_from_checkpoint(task: Callable[[DictConfig], Any], argv: list[str], command: str) -> int:
    """``launch`` with the config of ``checkpoint=<path>`` in ``argv``: its overrides, then the command's (which win).

    The model settings a default change would alter are restored from the checkpoint inside the task
    (``checkpoint_config``)."""
    if "--help" in argv or "-h" in argv:  # Hydra's help (config groups and options): no checkpoint needed
        return launch(task, argv, f"gpnerf_core {command}")
    given = [a for a in argv if a.startswith("checkpoint=")]
    if not given:
        raise GpnerfError(f"{command} needs checkpoint=<path to a .pt file written by run>")
    trained = load_trained(given[-1].split("=", 1)[1])  # the task reads the same file: not read again
    check_recorded_components(trained.state, trained.path)
    return launch(task, merge_overrides(trained.overrides, argv), f"gpnerf_core {command}")


def precheck(argv: list[str]) -> None:
    """Compose and validate the config before Hydra starts (and creates the run folder), so a bad override or value
    is one line and exit code 2. Sweeps (``-m``), Hydra's own flags and ``${hydra:...}`` values (which only resolve
    inside a job) are left to Hydra; every job validates too."""
    if any(argument.startswith("-") or "${hydra:" in argument for argument in argv):
        return
    overrides = [a for a in argv if not a.lstrip("+~").startswith(("hydra.", "hydra/")) or is_search_path(a)]
    cfg = compose_checked(overrides)
    if cfg.out_dir:
        check_writable_folder(Path(cfg.out_dir))
    else:
        check_default_output_root(Path("outputs"))


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


# -- 2. around the task: process group, one-line errors, sweep failure records ----------------------------------


def job(task: Callable[[DictConfig, Distributed], Any]) -> Callable[[DictConfig], Any]:
    """Make ``task(cfg, dist)`` a Hydra task: ``guarded`` around ``distributed``."""
    return guarded(distributed(task))


def distributed(task: Callable[[DictConfig, Distributed], Any]) -> Callable[[DictConfig], Any]:
    """Join the torchrun process group (if any) around ``task`` and leave it afterwards, whatever happens."""

    def wrapper(cfg: DictConfig) -> Any:
        dist = init_distributed(cfg.device)
        try:
            return task(cfg, dist)
        finally:
            dist.shutdown()

    wrapper.__name__ = task.__name__
    return wrapper


def guarded(task: Callable[[DictConfig], Any]) -> Callable[[DictConfig], Any]:
    """Errors caused by input or environment, faults of a plugin's code, and interruptions become one line on stderr
    and an exit code.

    Exit codes: 2 for a refused input or an environment fault (full disk, read-only folder); 1 for an exception raised
    in a component's code (a plugin's bug: the line names the component, its plugin and distribution); the signal's
    code for an interruption during training (after the checkpoint it wrote and the command that resumes from it are
    printed), 130 for Ctrl-C outside training. An exception raised in gpnerf-core's own code keeps its traceback. In
    a ``-m`` sweep a failing job does not stop the others: its error goes to ``error.json`` in its folder (never into
    a folder it was refused for) and the command exits 2 once the sweep is done. A failed job removes only what it
    created: the run files written before its first checkpoint, and the folders it made.
    """

    def wrapper(cfg: DictConfig) -> Any:
        hydra = hydra_config()
        if hydra is not None:
            adopt_new_folder(Path(hydra.runtime.output_dir))  # made by Hydra for this job
        try:
            return task(cfg)
        except (GpnerfError, OSError) as exc:
            if os.environ.get("GPNERF_DEBUG"):
                _remove_made_run_folder(cfg)
                raise
            message = str(exc)
            if isinstance(exc, OSError):  # an environment fault: a full disk, a vanished or read-only folder
                where = f"{exc.filename}: " if exc.filename else ""
                message = f"{where}{exc.strerror or exc}; the run stopped (free space, fix permissions or choose another folder)"
            return _fail(cfg, message, 2, refused_folder=isinstance(exc, RunFolderError))
        except RuntimeError as exc:
            if os.environ.get("GPNERF_DEBUG"):
                _remove_made_run_folder(cfg)
                raise
            if lost_peer(exc):
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                print(f"error: another process of the job stopped ({first[:160]}); under torchrun --max-restarts=N "
                      "with train.resume=auto the group restarts from the newest checkpoint", file=sys.stderr)
                sys.exit(1)
            fault = component_fault(cfg, exc)
            if fault is None:
                _remove_made_run_folder(cfg)
                raise
            return _fail(cfg, fault, 1)
        except TrainingInterrupted as stop:
            if stop.checkpoint is not None:
                print(
                    f"interrupted ({stop}): checkpoint {stop.checkpoint}; resume with: "
                    f"{resume_command(stop.checkpoint.parent.parent, stop.checkpoint)}",
                    file=sys.stderr,
                )
            sys.exit(stop.exit_code)
        except (KeyboardInterrupt, Terminated, Exception) as exc:
            # An Exception here may be a library's own error raised while an interruption unwound through it.
            stop = interrupted_by(exc)
            if stop is None:
                fault = None if os.environ.get("GPNERF_DEBUG") else component_fault(cfg, exc)
                if fault is None:
                    _remove_made_run_folder(cfg)
                    raise
                return _fail(cfg, fault, 1)
            name, code = interruption(stop)
            print(f"interrupted ({name}) outside the training loop; files already written stay", file=sys.stderr)
            sys.exit(code)

    wrapper.__name__ = task.__name__
    return wrapper


def _fail(cfg: DictConfig, message: str, code: int, *, refused_folder: bool = False) -> None:
    """Print ``message`` as the job's one line; in a sweep record it and go on, else remove the folders this command
    made (left empty) and exit with ``code``. ``refused_folder``: the job was refused the run folder itself."""
    print(f"error: {message}", file=sys.stderr)
    if in_sweep() and record_sweep_failure(cfg, message, refused_folder=refused_folder):
        return None
    _remove_made_run_folder(cfg)
    sys.exit(code)


def _remove_made_run_folder(cfg: DictConfig) -> None:
    """Remove the job's run folder if this command made it and it is empty (``remove_made_folders``)."""
    try:
        remove_made_folders(run_dir(cfg))
    except GpnerfError:
        pass


def component_fault(cfg: DictConfig, exc: BaseException) -> str | None:
    """The line for an exception raised in the code of a component ``cfg`` uses (a plugin's bug), naming the component,
    the plugin and the distribution that provide it and the exception's own first line; None when no component's code
    is in its traceback (a fault of gpnerf-core keeps its traceback), for an out-of-memory error and for an error
    raised while an interruption unwound (which stays an interruption)."""
    from gpnerf_core.registry.plugins import one_line

    if isinstance(exc, (MemoryError, torch.cuda.OutOfMemoryError)) or interrupted_by(exc) is not None:
        return None
    entry = _raising_component(exc, components_of(cfg))
    if entry is None:
        return None
    return (
        f"{entry.where} raised {type(exc).__name__}: {one_line(exc)}; a fault in that plugin's code: "
        "GPNERF_DEBUG=1 shows the traceback to report to its authors"
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


def _raising_component(exc: BaseException, components: dict[str, Any]) -> Any:
    """The component whose code the innermost frame of ``exc``'s traceback that lies in any component's code belongs
    to: a method of an instance of its class, or its factory's module, else its factory's package (None: none)."""
    frames = []
    tb = exc.__traceback__
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    factories = {kind: entry.spec.factory for kind, entry in components.items()}
    for frame in reversed(frames):
        module = str(frame.f_globals.get("__name__", ""))
        owner = frame.f_locals.get("self")
        for kind, factory in factories.items():
            if isinstance(factory, type) and isinstance(owner, factory) or module == factory.__module__:
                return components[kind]
        for kind, factory in factories.items():
            package = factory.__module__.rpartition(".")[0] or factory.__module__
            if module == package or module.startswith(package + "."):
                return components[kind]
    return None


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


def lost_peer(exc: BaseException) -> bool:
    """True for the error a collective raises when another process of the group died (gloo/NCCL)."""
    backend_error = getattr(torch.distributed, "DistBackendError", ())
    text = str(exc)
    return isinstance(exc, backend_error) or any(
        marker in text for marker in ("Connection closed by peer", "Connection reset by peer", "Broken pipe",
                                      "NCCL communicator was aborted")
    )


def in_sweep() -> bool:
    """True inside a job of a ``-m`` sweep."""
    from hydra.types import RunMode

    hydra = hydra_config()
    return hydra is not None and hydra.mode == RunMode.MULTIRUN


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
    return not folder.exists() or made_by_this_command(folder) or folder.absolute() in _CLAIMED_FOLDERS


_CLAIMED_FOLDERS: set[Path] = set()
"""Run folders this process claimed (``claim_run_folder``)."""


def resume_command(folder: Path, checkpoint: Path | None) -> str:
    """The command that resumes this run from ``checkpoint`` in the same folder (a torchrun line under torchrun):
    ``run``, or ``finetune`` with its ``checkpoint=`` (the start it fine-tunes from) kept."""
    command = sys.argv[0].split()[-1] if sys.argv and sys.argv[0].startswith("gpnerf_core ") else "run"
    dropped = [key for key in RUN_SPECIFIC_KEYS if not (command == "finetune" and key == "checkpoint")]
    kept = [o for o in task_overrides() if override_key(o) not in dropped]
    args = [*kept, f"out_dir={folder}", f"train.resume={checkpoint}"]
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1:
        local = os.environ.get("LOCAL_WORLD_SIZE", str(world))
        nodes = " (on every node, with the same --nnodes/--rdzv-endpoint)" if int(local) != world else ""
        launcher = f"torchrun --nproc_per_node={local} -m gpnerf_core {command}"
        return f"{launcher} {' '.join(shlex.quote(a) for a in args)}{nodes}"
    return f"python -m gpnerf_core {command} {' '.join(shlex.quote(a) for a in args)}"


# -- 3. inside the task: validate, seed, claim the folder --------------------------------------------------------


def start(cfg: DictConfig) -> None:
    """Refuse bad values before any work (a sweep's jobs share no fixed ``out_dir``), then ``setup_process``."""
    check_config(cfg)
    _refuse_shared_out_dir(cfg)
    setup_process(cfg)


def _refuse_shared_out_dir(cfg: DictConfig) -> None:
    """Under ``-m`` every job would write one fixed ``out_dir``: refuse unless it depends on the job."""
    if not in_sweep() or not cfg.out_dir:
        return
    raw = OmegaConf.to_container(cfg, resolve=False).get("out_dir")  # the interpolation as typed, before resolving
    if "${" not in str(raw):
        raise RunFolderError(
            f"out_dir={cfg.out_dir} with -m: every job of the sweep would write that one folder; leave out_dir "
            "unset (jobs go under hydra.sweep.dir) or make it depend on the job, e.g. 'out_dir=runs/${hydra:job.num}'"
        )


@dataclass(frozen=True)
class ResumePlan:
    """How a ``run`` starts: from ``checkpoint`` (None: from scratch), with notes to print; ``replace_leftovers``: the
    folder may hold files of an earlier attempt of this run that died before its first checkpoint (``resume=auto``),
    which the claim replaces."""

    checkpoint: Path | None
    notes: tuple[str, ...] = ()
    replace_leftovers: bool = False

    @property
    def resuming(self) -> bool:
        return self.checkpoint is not None


def plan_resume(cfg: DictConfig, dist: Distributed) -> ResumePlan:
    """Resolve ``train.resume`` (``auto``: rank 0 picks the newest intact checkpoint of ``out_dir`` and every rank takes
    the same) and check that the checkpoint can continue this config; ``cfg.train.resume`` becomes the path chosen.

    Every check of the checkpoint that refuses the resume runs before the run folder is touched: here the seed, the
    steps and (``train.resume_strict``) the model and loss config; the trainer's own (weights, optimizer state, weight
    average) run when it is built, which ``run`` does before it claims the folder.

    Raises:
        ConfigError: ``auto`` without ``out_dir``; another ``seed`` than the checkpoint's (its random streams go on,
            the new seed would be recorded but not used); ``train.steps`` below the checkpoint's step; another model
            or loss config (``check_resume_config``, unless ``train.resume_strict=false``).
        DataError: the checkpoint is missing, a folder or damaged; ``auto`` found only damaged ones.
    """
    value = cfg.train.resume
    if not value:
        return ResumePlan(None)
    notes: list[str] = []
    if str(value) == "auto":
        if not cfg.out_dir:
            raise ConfigError("train.resume=auto needs out_dir=<folder>: the fixed folder a restarted job resumes in")
        outcome = dist.broadcast_object(_find_auto_checkpoint(Path(str(cfg.out_dir))) if dist.is_main else None)
        if outcome[0] == "error":
            raise DataError(outcome[1])
        found, notes = outcome[1], list(outcome[2])
        with open_dict(cfg):
            cfg.train.resume = found
        if found is None:
            notes.append(f"train.resume=auto: no checkpoint in {cfg.out_dir}; training from the start")
            return ResumePlan(None, tuple(notes), replace_leftovers=True)
        notes.append(f"train.resume=auto: resuming from {found}")
    path = checked_checkpoint_path(str(cfg.train.resume), "train.resume")
    state = load_trained(path, "train.resume").state  # the trainer reads the same file: not read again
    written = OmegaConf.create(state["config"]) if state.get("config") else OmegaConf.create({})
    if "seed" in written and int(written.seed) != int(cfg.seed):
        raise ConfigError(
            f"train.resume={path}: seed={int(cfg.seed)} differs from the checkpoint's seed={int(written.seed)}; a "
            "resumed run continues the checkpoint's random streams, so leave seed as it was or start a new run"
        )
    if int(cfg.train.steps) < int(state["step"]):
        raise ConfigError(
            f"train.resume={path}: train.steps={int(cfg.train.steps)} is below the step {int(state['step'])} the "
            "checkpoint reached; give train.steps >= that step (equal: evaluate it again)"
        )
    if cfg.train.resume_strict:  # another model or loss: refused here, before anything is written
        check_resume_config(path, state["config"], OmegaConf.to_yaml(cfg, resolve=True), True)
    return ResumePlan(path, tuple(notes))


def _find_auto_checkpoint(folder: Path) -> tuple[str, Any, Any]:
    """``("ok", path or None, notes)`` for ``train.resume=auto`` in ``folder``, or ``("error", message, None)``."""
    try:
        found, notes = newest_intact_checkpoint(folder)
    except GpnerfError as exc:
        return ("error", str(exc), None)
    if found is None and (folder / "metrics.json").exists():
        return ("error", f"train.resume=auto: {folder} holds a finished run's metrics.json but no checkpoint to "
                         "resume from; choose another out_dir, or overwrite=true to replace it", None)
    return ("ok", None if found is None else str(found), notes)


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
        _CLAIMED_FOLDERS.add(folder_path.absolute())
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


# -- the job's Hydra context -------------------------------------------------------------------------------------


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


# -- commands that start from a checkpoint -----------------------------------------------------------------------


@dataclass(frozen=True)
class CheckpointModel:
    """A trained model rebuilt from its checkpoint for a command that uses it as it is (``eval``, ``render``, ``view``).

    Attributes:
        trained: the checkpoint (``load_trained``); notes: config keys restored from it, classes taken from it.
        components: built from the checkpoint's config plus the command's overrides, the model on the job's device
            holding the weights ``eval.weights`` chose; weights: which (``average`` or ``trained``).
    """

    trained: TrainedModel
    notes: list[str]
    components: Any
    weights: str
    fitted: FittedScenes | None = None
    """A per-scene model's scenes (``chosen_scene`` takes only those and defaults to its own); None for a generalizable
    one."""


def model_from_checkpoint(cfg: DictConfig, dist: Distributed, command: str, *, check_scenes: bool) -> CheckpointModel:
    """``checkpoint_config``, ``start``, ``built_from_checkpoint`` (``check_scenes``: ``check_data`` on the evaluated
    splits; a per-scene model is scored on its own scene only) and the model moved to the job's device. Nothing is
    written."""
    trained, notes = checkpoint_config(cfg, command)
    start(cfg)
    built = built_from_checkpoint(cfg, trained, str(cfg.eval.weights))
    components = built.components
    fitted = fitted_scenes(cfg, components, trained)
    if check_scenes:
        if fitted is not None:
            check_evaluated_scenes(cfg, components, fitted)
        check_data(cfg, components, training=False)
    components.model.to(dist.device)
    return CheckpointModel(trained, [*notes, *built.notes], components, built.weights, fitted)


@dataclass(frozen=True)
class BuiltFromCheckpoint:
    """A checkpoint's model built and loaded (``built_from_checkpoint``).

    Attributes:
        components: built from the config, the model holding the chosen weights; notes: the classes taken from the
            checkpoint (a dataset without a class list); weights: which (``average`` or ``trained``); reinitialised:
            the keys that kept a fresh initialisation for another class count (``new_classes``), with
            ``checkpoint_classes`` the checkpoint's class count.
    """

    components: Any
    notes: list[str]
    weights: str
    reinitialised: list[str]
    checkpoint_classes: int | None


def built_from_checkpoint(cfg: DictConfig, trained: TrainedModel, choice: str, *, new_classes: bool = False,
                          source: str | None = None) -> BuiltFromCheckpoint:
    """The one walk from a checkpoint to a built model (``eval``, ``render``, ``export``, ``view``, ``finetune``,
    ``stress``): the components of ``cfg`` built with the checkpoint's classes where the dataset has none, and the
    weights ``choice`` picks (``eval.weights``) loaded. ``new_classes``: a tensor sized by another class count keeps its
    initialisation (``finetune`` on another dataset); a shape that differs otherwise is blamed on the model keys that
    differ from the checkpoint's. ``source`` names the checkpoint in errors (default ``checkpoint <path>``)."""
    components = build_components(cfg, classes=trained.classes)
    notes = [components.classes.note(str(cfg.dataset.name))] if components.classes.from_checkpoint else []
    weights, which = trained.weights(choice)
    old = trained.classes.num_classes if trained.classes is not None else None
    current = OmegaConf.to_yaml(cfg, resolve=True)
    reinitialised = load_weights(
        components.model, weights, source or f"checkpoint {trained.path}",
        new_classes=(old, components.classes.num_classes) if new_classes and old is not None else None,
        explain=lambda: format_differences(model_differences(trained.config_yaml, current, trained.model_sections))
        or "no key (a different plugin version?)",
    )
    checkpoint_classes = int(weights[reinitialised[0]].shape[0]) if reinitialised else None
    return BuiltFromCheckpoint(components, notes, which, reinitialised, checkpoint_classes)


def fitted_scenes(cfg: DictConfig, components: Any, trained: TrainedModel) -> FittedScenes | None:
    """The scenes a per-scene model (``ModelFamily.generalizable`` False) was fitted on, from its checkpoint; None for a
    generalizable model, or a checkpoint that names none."""
    if components.model.generalizable or not trained.scenes:
        return None
    scenes = trained.scenes
    shown = f"scene {scenes[0]!r}" if len(scenes) == 1 else f"scenes {', '.join(map(repr, scenes))}"
    return FittedScenes(scenes, f"model {cfg.model.name!r} was fitted on {shown} alone (checkpoint {trained.path}): a "
                                "per-scene model renders only its scene")


def check_evaluated_scenes(cfg: DictConfig, components: Any, fitted: FittedScenes) -> None:
    """A per-scene model is scored on its own scene: any other scene of the evaluated splits is refused."""
    for split in cfg.eval.splits:
        foreign = [name for name in components.dataset.scenes(str(split)) if name not in fitted.scenes]
        if foreign:
            key = "dataset.scenes" if str(split) == "train" else "eval.splits"
            raise ConfigError(f"eval.splits has {split!r} with scene {foreign[0]!r}, but {fitted.why}; set "
                              f"dataset.scenes=[{','.join(fitted.scenes)}] and eval.splits=[train] ({key} names "
                              f"another scene)")


def checkpoint_config(cfg: DictConfig, command: str) -> tuple[TrainedModel, list[str]]:
    """Read ``cfg.checkpoint`` (``load_trained``) and give ``cfg`` its model settings wherever the command did not set
    them (``restore_model_settings``).

    Returns:
        the checkpoint and the notes on restored keys.
    """
    if not cfg.checkpoint:
        raise ConfigError(f"{command} needs checkpoint=<path to a .pt file written by run>")
    trained = load_trained(str(cfg.checkpoint))
    typed = [override_key(o) for o in task_overrides() if o not in trained.overrides]
    from gpnerf_core.config.legacy import DEFAULT_MODEL  # a config read back always names its family (legacy)

    family = str(((yaml.safe_load(trained.config_yaml) or {}).get("model") or {}).get("name") or DEFAULT_MODEL)
    if "model" in typed and str(cfg.model.name) != family:
        raise ConfigError(f"model={cfg.model.name}: checkpoint {trained.path} holds a trained model {family!r}; "
                          f"{command} takes its model family from the checkpoint: drop model=...")
    return trained, restore_model_settings(cfg, trained, typed)
