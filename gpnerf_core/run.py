"""The jobs behind ``run`` and ``eval``: compose, build, train, evaluate, write the run folder.

Both run as one process or as N under torchrun. Rank 0 alone writes the run folder, which it first locks
(``RunFolder``); every other process learns the folder from rank 0.
"""

from __future__ import annotations

import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Callable

import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from gpnerf_core.build import build_components
from gpnerf_core.distributed import Distributed, init_distributed
from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.io import atomic_write_json, atomic_write_text
from gpnerf_core.run_folder import RunFolder, RunFolderError, remove_untrained_run
from gpnerf_core.training.checkpoint import (
    MODEL_SECTIONS,
    NOT_MODEL_KEYS,
    RunRecord,
    config_differences,
    evaluation_weights,
    format_differences,
    load_weights,
    read_checkpoint,
)
from gpnerf_core.training.interrupt import TrainingInterrupted
from gpnerf_core.validation import check_data, validate_config

RUN_SPECIFIC_KEYS = ("checkpoint", "out_dir", "overwrite", "train.resume")
"""Overrides that name this run's files, not its model: never carried from a checkpoint into another run."""


def _hydra_config() -> Any:
    from hydra.core.hydra_config import HydraConfig

    return HydraConfig.get() if HydraConfig.initialized() else None


def _run_dir(cfg: DictConfig) -> Path:
    if cfg.out_dir:
        return Path(cfg.out_dir)
    hydra = _hydra_config()
    if hydra is None:
        raise ConfigError("out_dir is empty and no Hydra run directory exists; set out_dir=<folder>")
    return Path(hydra.runtime.output_dir)


def task_overrides() -> tuple[str, ...]:
    """The Hydra overrides of this job as typed (``+head=unet``, ``train.steps=10``, ...), and the search path if one
    was given (``eval``, ``finetune`` and resuming compose the checkpoint's overrides again and need it)."""
    from gpnerf_core.cli import is_search_path

    hydra = _hydra_config()
    if hydra is None:
        return ()
    return (*[o for o in hydra.overrides.hydra if is_search_path(o)], *hydra.overrides.task)


def override_key(override: str) -> str:
    """``+head=unet`` -> ``head``; ``train.steps=10`` -> ``train.steps``."""
    return override.split("=", 1)[0].lstrip("+~")


def _machine() -> dict[str, Any]:
    import platform

    return {
        "platform": platform.platform(),
        "processor": platform.machine(),
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }


def _record(cfg: DictConfig) -> RunRecord:
    from gpnerf_core.registry import KINDS, get_registry

    registry = get_registry()
    components = {}
    for kind in KINDS:
        node = cfg.get(kind)
        if node is not None and "name" in node and str(node.name) in registry.components[kind]:
            entry = registry.components[kind][str(node.name)]
            components[kind] = {"name": entry.spec.name, "provider": entry.provider, "version": entry.version}
    return RunRecord(
        config_yaml=OmegaConf.to_yaml(cfg, resolve=True), overrides=task_overrides(), components=components
    )


def _write_run_files(run_dir: Path, record: RunRecord) -> None:
    from gpnerf_core.registry import get_registry

    registry = get_registry()
    atomic_write_text(run_dir / "config.yaml", record.config_yaml)
    atomic_write_text(run_dir / "config.sha256", record.config_sha256 + "\n")
    atomic_write_text(run_dir / "overrides.yaml", OmegaConf.to_yaml(list(record.overrides)))
    atomic_write_json(
        run_dir / "plugins.json",
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


def _start(cfg: DictConfig) -> None:
    """Refuse bad values before any work, then set threads and the seed (which fixes the model's initialisation)."""
    validate_config(cfg)
    _refuse_shared_out_dir(cfg)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.seed))


def _prepare(cfg: DictConfig, dist: Distributed, *, resuming: bool) -> tuple[RunFolder, RunRecord]:
    """Rank 0 claims the run folder and writes what the run is made from."""
    run_dir = Path(dist.broadcast_object(str(_run_dir(cfg)) if dist.is_main else None))
    folder = RunFolder(run_dir)
    outcome: tuple[str, Any] = ("ok", [])
    if dist.is_main:
        try:
            outcome = ("ok", folder.claim(resuming=resuming, overwrite=bool(cfg.overwrite)))
        except GpnerfError as exc:
            outcome = ("error", str(exc))
    outcome = dist.broadcast_object(outcome)
    if outcome[0] == "error":
        raise RunFolderError(outcome[1])
    record = _record(cfg)
    if dist.is_main:
        for note in outcome[1]:
            print(f"note: {note}", file=sys.stderr)
        try:
            _write_run_files(run_dir, record)
        except BaseException:
            folder.release()
            raise
    return folder, record


def _refuse_shared_out_dir(cfg: DictConfig) -> None:
    """Under ``-m`` every job would write one fixed ``out_dir``: refuse unless it depends on the job."""
    from hydra.types import RunMode

    hydra = _hydra_config()
    if hydra is None or hydra.mode != RunMode.MULTIRUN or not cfg.out_dir:
        return
    typed = [o for o in task_overrides() if override_key(o) == "out_dir"]
    if not typed or "${" not in typed[-1]:
        raise ConfigError(
            f"out_dir={cfg.out_dir} with -m: every job of the sweep would write that one folder; leave out_dir "
            "unset (jobs go under hydra.sweep.dir) or make it depend on the job, e.g. 'out_dir=runs/${hydra:job.num}'"
        )


def resume_command(run_dir: Path, checkpoint: Path | None) -> str:
    """The command that resumes this run from ``checkpoint`` in the same folder."""
    kept = [o for o in task_overrides() if override_key(o) not in RUN_SPECIFIC_KEYS]
    args = [*kept, f"out_dir={run_dir}", f"train.resume={checkpoint}"]
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1:
        local = os.environ.get("LOCAL_WORLD_SIZE", str(world))
        nodes = " (on every node, with the same --nnodes/--rdzv-endpoint)" if int(local) != world else ""
        launcher = f"torchrun --nproc_per_node={local} -m gpnerf_core run"
        return f"{launcher} {' '.join(shlex.quote(a) for a in args)}{nodes}"
    return f"python -m gpnerf_core run {' '.join(shlex.quote(a) for a in args)}"


FAILED_SWEEP_JOBS: list[str] = []
"""Run folders of the jobs of this process's ``-m`` sweep that failed (the command exits 2 after the sweep)."""
ERROR_FILE = "error.json"


def _guarded(job: Callable[[DictConfig], Any]) -> Callable[[DictConfig], Any]:
    """Errors caused by input, and interruptions, become one line on stderr and an exit code, never a traceback.

    In a ``-m`` sweep a failing job does not stop the others: its error goes to ``error.json`` in its folder (which
    ``report`` shows as the row's error) and the command exits 2 once the sweep is done.
    """

    def wrapper(cfg: DictConfig) -> Any:
        try:
            return job(cfg)
        except (GpnerfError, OSError) as exc:
            if os.environ.get("GPNERF_DEBUG"):
                raise
            if isinstance(exc, OSError):  # an environment fault: a full disk, a vanished or read-only folder
                where = f"{exc.filename}: " if exc.filename else ""
                exc = f"{where}{exc.strerror or exc}; the run stopped (free space, fix permissions or choose another folder)"
            print(f"error: {exc}", file=sys.stderr)
            if _in_sweep() and _record_sweep_failure(cfg, str(exc)):
                return None
            _remove_if_empty(cfg)
            sys.exit(2)
        except TrainingInterrupted as stop:
            if stop.checkpoint is not None:
                print(
                    f"interrupted ({stop}): checkpoint {stop.checkpoint}; resume with: "
                    f"{resume_command(stop.checkpoint.parent.parent, stop.checkpoint)}",
                    file=sys.stderr,
                )
            sys.exit(stop.exit_code)
        except KeyboardInterrupt:
            print("interrupted (SIGINT) outside the training loop; files already written stay", file=sys.stderr)
            sys.exit(130)

    wrapper.__name__ = job.__name__
    return wrapper


def _in_sweep() -> bool:
    from hydra.types import RunMode

    hydra = _hydra_config()
    return hydra is not None and hydra.mode == RunMode.MULTIRUN


def _record_sweep_failure(cfg: DictConfig, message: str) -> bool:
    """Write ``error.json`` (the error and the job's overrides) into the job's folder; False if that is impossible."""
    try:
        run_dir = _run_dir(cfg)
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_json(run_dir / ERROR_FILE, {"error": message, "overrides": list(task_overrides())})
        if not (run_dir / "config.yaml").exists():
            atomic_write_text(run_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=False))
    except (GpnerfError, OSError, ValueError):
        return False
    FAILED_SWEEP_JOBS.append(str(run_dir))
    return True


def _remove_if_empty(cfg: DictConfig) -> None:
    """Hydra creates the run folder before the job starts: a job refused before training leaves none behind."""
    try:
        run_dir = _run_dir(cfg)
    except GpnerfError:
        return
    remove_untrained_run(run_dir)


def _distributed(job: Callable[[DictConfig, Distributed], Any]) -> Callable[[DictConfig], Any]:
    """Join the torchrun process group (if any) around ``job`` and leave it afterwards."""

    def wrapper(cfg: DictConfig) -> Any:
        dist = init_distributed(cfg.device)
        try:
            return job(cfg, dist)
        finally:
            dist.shutdown()

    wrapper.__name__ = job.__name__
    return wrapper


@_guarded
@_distributed
def run_task(cfg: DictConfig, dist: Distributed) -> dict[str, Any]:
    from gpnerf_core.evaluation.evaluator import evaluate, print_summary
    from gpnerf_core.evaluation.visualize import plot_training_curves
    from gpnerf_core.training.init_weights import init_weights
    from gpnerf_core.training.loggers import make_loggers
    from gpnerf_core.training.sampler import check_global_batch
    from gpnerf_core.training.trainer import Trainer

    _start(cfg)
    check_global_batch(int(cfg.train.targets_per_step), dist.world_size)
    resuming = bool(cfg.train.resume)
    components = build_components(cfg)
    check_data(cfg, components, training=True)
    if cfg.model.init and not resuming:
        report = init_weights(components.model, Path(cfg.model.init), strict=bool(cfg.model.init_strict))
        if dist.is_main:
            print(report, file=sys.stderr)
    folder, record = _prepare(cfg, dist, resuming=resuming)
    run_dir = folder.path
    with folder:
        trainer = Trainer(cfg, components, dist=dist, run_dir=run_dir, record=record)
        if dist.is_main:
            for note in trainer.notes:
                print(f"note: {note}", file=sys.stderr)
            if dist.enabled:
                print(
                    f"distributed: {dist.world_size} processes ({dist.backend}), "
                    f"{trainer.sampler.targets_per_rank} target view(s) each, "
                    f"{int(cfg.train.rays) * int(cfg.train.targets_per_step)} rays per step in all",
                    file=sys.stderr,
                )
        loggers = make_loggers(list(cfg.train.loggers), run_dir, trainer.resumed_step) if dist.is_main else []
        try:
            started = time.perf_counter()
            curve = _evaluated_curve(cfg, components, trainer, run_dir, dist, loggers)
            result = trainer.fit(progress=True, loggers=loggers)
            if dist.is_main:
                atomic_write_json(run_dir / "training_curves.json", result.history)
                if result.history:
                    loss_keys = [*trainer.loss_names, "loss"]
                    plot_training_curves(result.history, run_dir / "training_curves.png", loss_keys=loss_keys)
            with trainer.evaluation_weights() as weights:
                evaluation = evaluate(cfg, components, trainer.frames, run_dir, dist)
            metrics = {
                "config_sha256": record.config_sha256,
                "seed": int(cfg.seed),
                "machine": _machine(),
                "train": {
                    "steps": result.steps,
                    "seconds": round(result.seconds, 2),
                    "rays_per_second": round(result.rays_per_second, 1),
                    "final_loss": result.history[-1]["loss"] if result.history else None,
                    "checkpoint": str(result.checkpoint) if result.checkpoint else None,
                    "world_size": result.world_size,
                    "targets_per_step": int(cfg.train.targets_per_step),
                    "targets_per_rank": result.targets_per_rank,
                    "rays_per_step": result.rays_per_step,
                    "backend": dist.backend,
                    "precision": str(cfg.train.precision),
                },
                "evaluated_weights": weights,
                "parameters": components.model.parameter_counts(),
                **evaluation,
                "wall_seconds": round(time.perf_counter() - started, 2),
            }
            if curve:
                metrics["eval_curve"] = [*curve, curve_entry(result.steps, result.seconds, evaluation)]
            if dist.is_main:
                for logger in loggers:
                    logger.log(result.steps, eval_scalars(evaluation))
                atomic_write_json(run_dir / "metrics.json", metrics)
                print_summary(metrics, run_dir)
        finally:
            for logger in loggers:
                logger.close()
    return metrics


def curve_entry(step: int, seconds: float, evaluation: dict[str, Any]) -> dict[str, Any]:
    """One point of an accuracy curve: the step, the training seconds so far and each split's ``CURVE_KEYS``."""
    from gpnerf_core.finetune import CURVE_KEYS

    entry: dict[str, Any] = {"step": step, "train_seconds": round(seconds, 2)}
    for split, values in evaluation.get("eval", {}).items():
        entry[split] = {key: values[key] for key in CURVE_KEYS if key in values}
    return entry


def _evaluated_curve(cfg: DictConfig, components: Any, trainer: Any, run_dir: Path, dist: Distributed,
                     loggers: list[Any]) -> list[dict[str, Any]]:
    """With ``eval.every_steps``: train to every multiple of it below ``train.steps`` and evaluate there (no pictures;
    a checkpoint at each). Evaluation draws no random numbers, so the training after it is the training without it."""
    from gpnerf_core.evaluation.evaluator import evaluate

    every, total = int(cfg.eval.every_steps), int(cfg.train.steps)
    curve: list[dict[str, Any]] = []
    if not every:
        return curve
    for point in range(every, total, every):
        if point <= trainer.step:
            continue
        with open_dict(cfg):
            cfg.train.steps, saved_images = point, cfg.eval.save_images
            cfg.eval.save_images = 0
        try:
            trainer.fit(progress=True, loggers=loggers)
            with trainer.evaluation_weights():
                evaluation = evaluate(cfg, components, trainer.frames, run_dir, dist)
        finally:
            with open_dict(cfg):
                cfg.train.steps, cfg.eval.save_images = total, saved_images
        curve.append(curve_entry(trainer.step, trainer.elapsed, evaluation))
        if dist.is_main:
            for logger in loggers:
                logger.log(trainer.step, eval_scalars(evaluation))
            shown = ", ".join(
                f"{split} {values.get('miou/image_mean_present', values.get('psnr/clamped', float('nan'))):.3f}"
                for split, values in evaluation["eval"].items() if isinstance(values, dict)
            )
            print(f"eval at step {trainer.step}: {shown}", file=sys.stderr)
    return curve


@_guarded
@_distributed
def finetune_task(cfg: DictConfig, dist: Distributed) -> dict[str, Any]:
    from gpnerf_core.finetune import finetune_task_body

    return finetune_task_body(cfg, dist)


@_guarded
@_distributed
def render_task(cfg: DictConfig, dist: Distributed) -> dict[str, Any]:
    from gpnerf_core.render_video import render_task_body

    return render_task_body(cfg, dist)


def eval_scalars(evaluation: dict[str, Any]) -> dict[str, float]:
    """The numeric top-level metrics of every split as ``eval/<split>/<protocol id>`` tags."""
    scalars = {}
    for split, values in evaluation.get("eval", {}).items():
        for key, value in values.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                scalars[f"eval/{split}/{key}"] = float(value)
        for key, value in values.get("timing", {}).items():
            if isinstance(value, (int, float)):
                scalars[f"eval/{split}/timing/{key}"] = float(value)
    return scalars


@_guarded
@_distributed
def eval_task(cfg: DictConfig, dist: Distributed) -> dict[str, Any]:
    from gpnerf_core.evaluation.evaluator import evaluate, print_summary
    from gpnerf_core.frames import FrameCache

    checkpoint, state, notes = checkpoint_config(cfg, "eval")
    _start(cfg)
    components = build_components(cfg)
    check_data(cfg, components, training=False)
    weights, which = evaluation_weights(state, str(cfg.eval.weights))
    load_weights(components.model, weights, f"checkpoint {checkpoint}")
    components.model.to(dist.device)
    folder, record = _prepare(cfg, dist, resuming=False)
    with folder:
        if dist.is_main:
            ignore = ("checkpoint", "out_dir", "overwrite")
            differences = config_differences(state["config"], record.config_yaml, ignore=ignore)
            if differences:
                print(f"eval: differences from the checkpoint's config: {format_differences(differences)}",
                      file=sys.stderr)
            for note in notes:
                print(f"note: {note}", file=sys.stderr)
        evaluation = evaluate(cfg, components, FrameCache(components.dataset, dist.device), folder.path, dist)
        metrics = {
            "checkpoint": str(checkpoint),
            "checkpoint_step": state["step"],
            "checkpoint_config_sha256": state["config_sha256"],
            "evaluated_weights": which,
            "config_sha256": record.config_sha256,
            "machine": _machine(),
            "parameters": components.model.parameter_counts(),
            **evaluation,
        }
        if dist.is_main:
            atomic_write_json(folder.path / "metrics.json", metrics)
            print_summary(metrics, folder.path)
    return metrics


def checkpoint_config(cfg: DictConfig, command: str) -> tuple[Path, dict[str, Any], list[str]]:
    """Read ``cfg.checkpoint`` and give ``cfg`` its model settings (``restore_model_config``).

    Returns:
        the checkpoint's path, its contents and the notes on restored keys.
    """
    if not cfg.checkpoint:
        raise ConfigError(f"{command} needs checkpoint=<path to a .pt file written by run>")
    checkpoint = Path(str(cfg.checkpoint))
    state = read_checkpoint(checkpoint)
    return checkpoint, state, restore_model_config(cfg, state["config"], state.get("overrides", []))


def restore_model_config(cfg: DictConfig, checkpoint_yaml: str, checkpoint_overrides: list[str]) -> list[str]:
    """Give ``cfg`` the checkpoint's model and loss settings wherever this command did not override them.

    ``eval`` composes its config from the checkpoint's overrides plus the user's; if a default changed since the
    checkpoint was written, the recomposed model would differ from the trained one. Such keys are set back to the
    checkpoint's values (and reported); keys the user overrode keep the user's value.
    """
    typed = [override_key(o) for o in task_overrides() if o not in checkpoint_overrides]
    current = OmegaConf.to_yaml(cfg, resolve=True)
    restored = []
    for key, old, _ in config_differences(checkpoint_yaml, current, MODEL_SECTIONS, NOT_MODEL_KEYS):
        if any(key == t or key.startswith(t + ".") for t in typed):
            continue
        with open_dict(cfg):
            if old == "<absent>":
                parent, _, leaf = key.rpartition(".")
                node = OmegaConf.select(cfg, parent) if parent else cfg
                node.pop(leaf, None)
            else:
                OmegaConf.update(cfg, key, old, merge=False)
        restored.append(key)
    if not restored:
        return []
    return [f"kept the checkpoint's value of {', '.join(restored)} (the defaults changed since it was written)"]
