"""``python -m gpnerf_core run [overrides]``: train on the dataset's training scenes, then evaluate held-out views and
unseen scenes, and write the run folder (the main job; ``-m`` sweeps).

Runs as one process or as N under torchrun. Rank 0 alone writes the run folder, which it first locks
(``runs.claim_run_folder``); every other process learns the folder from rank 0. Everything that can refuse the run
(the config, the data, every check of the checkpoint it resumes from) happens before that claim: a refused command
leaves the folder as it was.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from gpnerf_core.interfaces.model import parameter_counts
from gpnerf_core.model.build import build_components
from gpnerf_core.runtime.device import machine_info
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.evaluation.curves import curve_entry, eval_scalars
from gpnerf_core.runtime.io import atomic_write_json
from gpnerf_core.engine.guarding import job
from gpnerf_core.engine.launching import Handover, launch
from gpnerf_core.engine.resuming import plan_resume
from gpnerf_core.engine.runs import claim_run_folder, run_record, shared_run_dir
from gpnerf_core.engine.setup import start
from gpnerf_core.engine.validation import check_data


def main(argv: list[str]) -> int:
    return launch(run_task, argv, "gpnerf_core run")


@job
def run_task(cfg: DictConfig, dist: Distributed, handover: Handover = Handover()) -> dict[str, Any]:
    from gpnerf_core.evaluation.evaluator import check_splits_have_frames, evaluate, print_summary
    from gpnerf_core.evaluation.visualize import plot_training_curves
    from gpnerf_core.model.weights import init_weights
    from gpnerf_core.training.loggers import make_loggers
    from gpnerf_core.training.sampler import check_global_batch
    from gpnerf_core.training.trainer import Trainer

    start(cfg, validated=handover.validated)
    check_global_batch(int(cfg.train.targets_per_step), dist.world_size)
    plan = plan_resume(cfg, dist)
    resuming = plan.resuming
    components = build_components(cfg)
    check_data(cfg, components, training=True)
    # An evaluation that would score nothing is refused before training (eval.splits=[] asks for none: no check).
    split_notes = check_splits_have_frames(cfg, components) if list(cfg.eval.splits) else []
    if cfg.model.init and not resuming:
        report = init_weights(components.model, Path(cfg.model.init), strict=bool(cfg.model.init_strict))
        if dist.is_main:
            print(report, file=sys.stderr)
    record = run_record(cfg, components.model_sections)
    run_dir = shared_run_dir(cfg, dist)
    trainer = Trainer(cfg, components, dist=dist, run_dir=run_dir, record=record,  # resumes: its checks refuse here
                      resume_from=plan.take_read())
    folder, record = claim_run_folder(
        cfg, dist, resuming=resuming, replace_leftovers=plan.replace_leftovers, record=record
    )
    with folder:
        if dist.is_main:
            for note in (*plan.notes, *trainer.notes, *split_notes):
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
            curve: list[dict[str, Any]] = []
            points = _curve_points(cfg, components, trainer, run_dir, dist, loggers, curve)
            result = trainer.fit(progress=True, loggers=loggers, callbacks=[points] if points else ())
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
                "machine": machine_info(),
                "train": result.metrics(cfg.train, dist.backend),
                "evaluated_weights": weights,
                "parameters": parameter_counts(components.model),
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


def _curve_points(cfg: DictConfig, components: Any, trainer: Any, run_dir: Path, dist: Distributed,
                  loggers: list[Any], entries: list[dict[str, Any]]) -> Any:
    """``evaluate_at`` with ``eval.every_steps`` (None without): evaluate at every multiple of it below
    ``train.steps`` (no pictures; a checkpoint at each), while training, the entries appended to ``entries``.
    Evaluation draws no random numbers, so the training around it is the training without it."""
    from gpnerf_core.evaluation.evaluator import evaluate
    from gpnerf_core.training.callbacks import evaluate_at

    every, total = int(cfg.eval.every_steps), int(cfg.train.steps)
    if not every:
        return None

    def evaluate_point() -> dict[str, Any]:
        with trainer.evaluation_weights():
            evaluation = evaluate(cfg, components, trainer.frames, run_dir, dist, pictures=False)
        if dist.is_main:
            for logger in loggers:
                logger.log(trainer.step, eval_scalars(evaluation))
            shown = ", ".join(f"{split} {_headline(values)}" for split, values in evaluation["eval"].items()
                              if isinstance(values, dict))
            print(f"eval at step {trainer.step}: {shown}", file=sys.stderr)
        return curve_entry(trainer.step, trainer.training_seconds, evaluation)

    return evaluate_at([p for p in range(every, total, every) if p > trainer.step], evaluate_point, entries)


def _headline(values: dict[str, Any]) -> str:
    """A split's per-image mIoU, or its PSNR where labels are not available (an unlabelled capture)."""
    for key, name in (("miou/image_mean_present", "mIoU"), ("psnr/clamped", "PSNR")):
        if values.get(key) is not None:
            return f"{name} {values[key]:.3f}"
    return "n/a"
