"""``python -m gpnerf_core eval checkpoint=<.pt> [overrides]``: evaluate a checkpoint with the config it was trained
with (recomposed from its overrides plus the command's) and write ``metrics.json`` into a new run folder."""

from __future__ import annotations

import sys
from typing import Any

from omegaconf import DictConfig

from gpnerf_core.interfaces.model import parameter_counts
from gpnerf_core.runtime.device import machine_info
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.runtime.io import atomic_write_json
from gpnerf_core.config.overrides import foreign_dataset_note
from gpnerf_core.engine.guarding import job
from gpnerf_core.engine.launching import Handover, launch_from_checkpoint
from gpnerf_core.engine.opening import open_trained
from gpnerf_core.engine.runs import claim_run_folder, task_overrides
from gpnerf_core.model.checkpoint import config_differences, format_differences


def main(argv: list[str]) -> int:
    return launch_from_checkpoint(eval_task, argv, "eval")


@job
def eval_task(cfg: DictConfig, dist: Distributed, handover: Handover = Handover()) -> dict[str, Any]:
    from gpnerf_core.evaluation.evaluator import check_splits_have_frames, evaluate, print_summary
    from gpnerf_core.data.frames import FrameCache

    opened = open_trained(handover.trained, cfg=cfg, command="eval", validated=handover.validated, device=dist.device,
                          check_scenes=True)
    trained, notes, components, which = opened.trained, opened.notes, opened.components, opened.weights
    notes = [*notes, *check_splits_have_frames(cfg, components)]  # refused here: before the run folder is claimed
    dataset_note = foreign_dataset_note(trained.overrides, list(task_overrides()))
    notes = [dataset_note, *notes] if dataset_note else notes
    folder, record = claim_run_folder(cfg, dist, resuming=False)
    with folder:
        if dist.is_main:
            ignore = ("checkpoint", "out_dir", "overwrite")
            differences = config_differences(trained.config_yaml, record.config_yaml, ignore=ignore)
            if differences:
                print(f"eval: differences from the checkpoint's config: {format_differences(differences)}",
                      file=sys.stderr)
            for note in notes:
                print(f"note: {note}", file=sys.stderr)
        evaluation = evaluate(cfg, components, FrameCache(components.dataset, dist.device), folder.path, dist)
        metrics = {
            "checkpoint": str(trained.path),
            "checkpoint_step": trained.step,
            "checkpoint_config_sha256": trained.config_sha256,
            "evaluated_weights": which,
            "config_sha256": record.config_sha256,
            "machine": machine_info(),
            "parameters": parameter_counts(components.model),
            **evaluation,
        }
        if dist.is_main:
            atomic_write_json(folder.path / "metrics.json", metrics)
            print_summary(metrics, folder.path)
    return metrics
