"""Accuracy curves: evaluations at several step counts of one training (``run``'s ``eval_curve``, ``finetune``'s
``curve``), and the scalars an evaluation gives the training loggers."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from gpnerf_core.errors import ConfigError, DataError

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


FIT_KEYS = ("miou/image_mean_present", "miou/dataset", "psnr/clamped")
"""Metrics of the held-out frames a ``fit`` curve point keeps (those the evaluation gives), besides ``fit.metric``."""


def fit_entry(step: int, train_seconds: float, start_seconds: float, gaussians: int, held_out: dict[str, Any],
              metric: str) -> dict[str, Any]:
    """One point of a ``fit`` curve: the step, the training seconds, ``seconds`` (the start's seconds plus the
    training seconds, from the start: 0 for a start from the scene's points), the family's Gaussian count and the
    held-out frames' ``FIT_KEYS`` and ``metric`` that the evaluation gave."""
    entry: dict[str, Any] = {"step": int(step), "train_seconds": round(train_seconds, 2),
                             "seconds": round(start_seconds + train_seconds, 2), "gaussians": int(gaussians)}
    entry.update({key: held_out[key] for key in (*FIT_KEYS, metric) if key in held_out})
    return entry


def check_fit_metric(metric: str, held_out: dict[str, Any], needed: bool, scene: str) -> None:
    """Refuse ``fit.metric`` when the held-out evaluation gives no such value (naming those it gives), or, where a
    stop rule reads it (``needed``), gives None (a scene without labels: ``psnr/clamped`` advised)."""
    scalars = sorted(key for key, value in held_out.items() if value is None or (
        isinstance(value, (int, float)) and not isinstance(value, bool)))
    if metric not in held_out or metric not in scalars:
        given = ", ".join(key for key in scalars if held_out[key] is not None)
        raise ConfigError(f"fit.metric={metric}: the evaluation of the held-out frames of scene {scene!r} gives no "
                          f"such value; expected one of: {given}")
    if needed and held_out[metric] is None:
        why = held_out.get("labels/unavailable_reason") or "it is not scored on these frames"
        raise ConfigError(f"fit.metric={metric}: the held-out frames of scene {scene!r} give no value of it ({why}), so "
                          "fit.target and fit.patience cannot read it; expected a metric they give, e.g. "
                          "fit.metric=psnr/clamped")


def curve_so_far(path: Path, step: int, what: str) -> list[dict[str, Any]]:
    """The points of a ``what`` curve (``fine-tuning``, ``fit``) an interrupted command evaluated up to ``step`` (the
    checkpoint it resumes from), read from ``path``; none when there is no file. A damaged file is refused naming it."""
    if not path.is_file():
        return []
    try:
        saved = json.loads(path.read_text())
    except ValueError:
        raise DataError(f"{path}: not a {what} curve (damaged JSON); delete it to evaluate those points again") from None
    if not isinstance(saved, list):
        raise DataError(f"{path}: not a {what} curve (expected a list of points); delete it to evaluate them again")
    return [entry for entry in saved if isinstance(entry, dict) and int(entry.get("step", -1)) <= step]
