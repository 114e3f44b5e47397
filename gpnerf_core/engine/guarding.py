"""Around every Hydra job: the torchrun process group (``distributed``) and one line plus an exit code for every error
caused by input or environment, a plugin's fault or an interruption (``guarded``); ``job`` is both.

Exit codes: 2 for a refused input or an environment fault, 1 for a fault in a component's code (a plugin's bug), the
signal's for an interruption during training (after printing the command that resumes it), 130 for Ctrl-C outside
training. In a ``-m`` sweep a failing job records its error and the others go on (``engine.sweeps``).
"""

from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path
from typing import Any, Callable

import torch
from omegaconf import DictConfig

from gpnerf_core.config.overrides import RUN_SPECIFIC_KEYS, override_key
from gpnerf_core.engine.runs import components_of, hydra_config, run_dir, task_overrides
from gpnerf_core.engine.sweeps import in_sweep, record_sweep_failure
from gpnerf_core.errors import GpnerfError
from gpnerf_core.runtime.distributed import init_distributed
from gpnerf_core.runtime.run_folder import RunFolderError, adopt_new_folder, remove_made_folders
from gpnerf_core.runtime.signals import Terminated, interrupted_by, interruption
from gpnerf_core.training.interrupt import TrainingInterrupted


def job(task: Callable[..., Any]) -> Callable[..., Any]:
    """Make ``task(cfg, dist, *handed)`` a Hydra task ``(cfg, *handed)``: ``guarded`` around ``distributed``.

    ``handed``: what the launcher hands the job (``launching.Handover``: the config validated, the checkpoint read);
    ``launch`` passes it, a caller outside Hydra (a test, a notebook) may leave it out."""
    return guarded(distributed(task))


def distributed(task: Callable[..., Any]) -> Callable[..., Any]:
    """Join the torchrun process group (if any) around ``task(cfg, dist, *handed)`` and leave it afterwards, whatever
    happens."""

    def wrapper(cfg: DictConfig, *handed: Any) -> Any:
        dist = init_distributed(cfg.device)
        try:
            return task(cfg, dist, *handed)
        finally:
            dist.shutdown()

    wrapper.__name__ = task.__name__
    return wrapper


def guarded(task: Callable[..., Any]) -> Callable[..., Any]:
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

    def wrapper(cfg: DictConfig, *handed: Any) -> Any:
        hydra = hydra_config()
        if hydra is not None:
            adopt_new_folder(Path(hydra.runtime.output_dir))  # made by Hydra for this job
        try:
            return task(cfg, *handed)
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


def lost_peer(exc: BaseException) -> bool:
    """True for the error a collective raises when another process of the group died (gloo/NCCL)."""
    backend_error = getattr(torch.distributed, "DistBackendError", ())
    text = str(exc)
    return isinstance(exc, backend_error) or any(
        marker in text for marker in ("Connection closed by peer", "Connection reset by peer", "Broken pipe",
                                      "NCCL communicator was aborted")
    )


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
