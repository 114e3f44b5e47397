"""``python -m gpnerf_core finetune checkpoint=<run's .pt> dataset.scenes=[...] train.steps=N``: per-scene fine-tuning.

Starts from a generalized checkpoint (its config, recomposed from its overrides plus the command's, and its weights),
trains on the chosen scenes' training frames only and evaluates their held-out frames, which are never trained on
(the paper's Table 1 "fine-tuning" and Table 2's per-scene setting). The held-out frames are evaluated at several
step counts (``finetune.points``, default 0, N/4, N/2, N), so ``metrics.json`` holds the curve of accuracy against
fine-tuning steps and seconds. A dataset with another class count re-initialises only the head's tensors that carry
the class dimension (its last layer) and says so; any other mismatch names the config keys that differ. A dataset
without a class list (a capture without labels) keeps the checkpoint's classes; on scenes without labels, fine-tune
with a loss set that needs none (``+loss=label_free``): the label metrics of the curve are then None.
"""

from __future__ import annotations

import sys
import time
from typing import Any

from omegaconf import DictConfig, open_dict

from gpnerf_core.runtime.device import machine_info
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation.curves import CURVE_KEYS, curve_points, curve_so_far
from gpnerf_core.runtime.io import atomic_write_json
from gpnerf_core.config.overrides import foreign_dataset_note
from gpnerf_core.engine.guarding import job
from gpnerf_core.engine.launching import Handover, launch_from_checkpoint
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.engine.resuming import plan_resume
from gpnerf_core.engine.runs import claim_run_folder, run_record, shared_run_dir, task_overrides
from gpnerf_core.engine.validation import check_data


def main(argv: list[str]) -> int:
    return launch_from_checkpoint(finetune_task, argv, "finetune")


@job
def finetune_task(cfg: DictConfig, dist: Distributed, handover: Handover = Handover()) -> dict[str, Any]:
    from gpnerf_core.evaluation.evaluator import check_splits_have_frames, evaluate, print_summary
    from gpnerf_core.training.callbacks import evaluate_at
    from gpnerf_core.training.trainer import Trainer

    scenes = list(cfg.dataset.get("scenes") or [])
    if not scenes:
        raise ConfigError(
            "finetune needs dataset.scenes=[<scene>, ...]: the scenes to fine-tune on (their held-out frames are "
            "evaluated, never trained on)"
        )
    total = int(cfg.train.steps)
    points = curve_points(total, int(cfg.finetune.points))
    with open_dict(cfg):
        cfg.eval.splits = ["train"]  # the chosen scenes' held-out frames
    opened = open_trained(handover.trained, cfg=cfg, command="finetune", validated=handover.validated,
                          device=dist.device, new_classes=True, other_data=True, source="finetune checkpoint={path}")
    trained, components, which, reinitialised = opened.trained, opened.components, opened.weights, opened.reinitialised
    checkpoint, notes = trained.path, opened.notes
    plan = plan_resume(cfg, dist)  # train.resume: an interrupted fine-tuning's own checkpoint (or auto)
    check_data(cfg, components, training=True)
    check_splits_have_frames(cfg, components)  # the chosen scenes' held-out frames: a curve of no image is refused
    dataset_note = foreign_dataset_note(trained.overrides, list(task_overrides()))
    notes = [dataset_note, *notes] if dataset_note else notes
    record = run_record(cfg, components.model_sections)
    run_dir = shared_run_dir(cfg, dist)
    trainer = Trainer(cfg, components, dist=dist, run_dir=run_dir, record=record,  # resumes: refused before the claim
                      resume_from=plan.take_read())
    folder, record = claim_run_folder(
        cfg, dist, resuming=plan.resuming, replace_leftovers=plan.replace_leftovers, record=record
    )
    with folder:
        if dist.is_main:
            for note in (*notes, *plan.notes):
                print(f"note: {note}", file=sys.stderr)
            if reinitialised:
                print(
                    f"note: {components.classes.num_classes} classes instead of the checkpoint's "
                    f"{opened.checkpoint_classes}: "
                    f"re-initialised {', '.join(reinitialised)} (the head's last layer); every other tensor loaded",
                    file=sys.stderr,
                )
            print(f"finetune: {', '.join(scenes)} from {checkpoint} (step {trained.step}, {which} weights); "
                  f"evaluating at steps {', '.join(map(str, points))}", file=sys.stderr)
        started = time.perf_counter()
        curve = curve_so_far(run_dir / CURVE_FILE, trainer.step, "fine-tuning") if plan.resuming else []
        evaluation: dict[str, Any] = {}

        def evaluate_point() -> dict[str, Any]:
            nonlocal curve, evaluation
            evaluation = evaluate(cfg, components, trainer.frames, run_dir, dist)
            held_out = evaluation["eval"].get("train_heldout", {})
            entry = {"step": trainer.step, "train_seconds": round(trainer.training_seconds, 2)}
            entry.update({key: held_out[key] for key in CURVE_KEYS if key in held_out})
            curve = [*(e for e in curve if e["step"] != entry["step"]), entry]
            if dist.is_main:
                atomic_write_json(run_dir / CURVE_FILE, curve)
                shown = ", ".join(f"{k} {v:.3f}" for k, v in entry.items() if k in CURVE_KEYS and v is not None)
                print(f"finetune step {trainer.step}: {shown}", file=sys.stderr)
            return entry

        done = {entry["step"] for entry in curve}
        pending = [point for point in points if point >= trainer.step and (point not in done or point == total)]
        if trainer.step in pending and trainer.step < total:  # the start, or a point reached before an interruption
            evaluate_point()
        trainer.fit(progress=True, callbacks=[evaluate_at([p for p in pending if trainer.step < p < total],
                                                          evaluate_point)])
        evaluate_point()  # the last point: train.steps
        rays_per_step = int(cfg.train.rays) * int(cfg.train.targets_per_step)
        metrics = {
            "config_sha256": record.config_sha256,
            "seed": int(cfg.seed),
            "machine": machine_info(),
            "finetune": {
                "checkpoint": str(checkpoint),
                "checkpoint_step": trained.step,
                "checkpoint_config_sha256": trained.config_sha256,
                "scenes": scenes,
                "reinitialised": reinitialised,
                "curve": curve,
            },
            "train": {
                "steps": trainer.step,
                "seconds": round(trainer.elapsed, 2),
                "rays_per_second": round(rays_per_step * trainer.step / trainer.elapsed, 1) if trainer.elapsed else 0.0,
                "final_loss": trainer.history[-1]["loss"] if trainer.history else None,
            },
            **evaluation,
            "wall_seconds": round(time.perf_counter() - started, 2),
        }
        if dist.is_main:
            atomic_write_json(run_dir / "metrics.json", metrics)
            print_summary(metrics, run_dir)
    return metrics


CURVE_FILE = "finetune_curve.json"
"""The curve's points evaluated so far, rewritten after each: a resumed fine-tuning keeps them."""
