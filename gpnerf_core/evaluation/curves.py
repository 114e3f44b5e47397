"""Accuracy curves: evaluations at several step counts of one training (``run``'s ``eval_curve``, ``finetune``'s
``curve``), and the scalars an evaluation gives the training loggers."""

from __future__ import annotations

from typing import Any

from gpnerf_core.errors import ConfigError

CURVE_KEYS = (
    "miou/image_mean_present",
    "miou/dataset",
    "acc/total",
    "psnr/clamped",
    "ssim/gaussian11",
    "instance/ap_matched@0.75",
    "instance/coco_mask_ap",
)
"""Metrics a curve entry keeps for each evaluated split (``finetune.curve``, ``eval_curve`` of ``run``)."""


def curve_points(steps: int, points: int) -> list[int]:
    """``points`` step counts from 0 to ``steps`` evenly (0, N/4, N/2, 3N/4, N for 5), distinct and ascending."""
    if points < 2:
        raise ConfigError(f"finetune.points={points}: expected at least 2 (before fine-tuning and after it)")
    return sorted({round(steps * k / (points - 1)) for k in range(points)})


def curve_entry(step: int, seconds: float, evaluation: dict[str, Any]) -> dict[str, Any]:
    """One point of an accuracy curve: the step, the training seconds so far and each split's ``CURVE_KEYS``."""
    entry: dict[str, Any] = {"step": step, "train_seconds": round(seconds, 2)}
    for split, values in evaluation.get("eval", {}).items():
        entry[split] = {key: values[key] for key in CURVE_KEYS if key in values}
    return entry


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
