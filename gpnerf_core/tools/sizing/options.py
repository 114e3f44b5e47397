"""The ``size.*`` options of ``python -m gpnerf_core size``, parsed and checked (one line per bad value)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation.evaluator import SPLIT_LABELS
from gpnerf_core.tools.sizing.knobs import known_knobs

METRICS = {"miou": ("train_heldout", "miou/image_mean_present"),
           "ap75": ("train_heldout", "instance/ap_matched@0.75"), "psnr": ("train_heldout", "psnr/clamped")}
"""Selection metric -> where it is in ``metrics.json`` (held-out views of the training scenes, never unseen scenes)."""
DEFAULT_TOLERANCE = {"miou": 0.02, "ap75": 0.02, "psnr": 0.5}
PREDICTS_METRIC = {"classes": "miou", "instances": "ap75"}
"""The default metric by what the model predicts (``psnr`` for colour only)."""
NUMBERS: dict[str, tuple] = {
    "steps": (int, 0),
    "seeds": (int, 1, 10),
    "min_coverage": (float, 0.0, 1.0),
    "depth_margin": (float, 0.0, 0.9),
}
"""Numeric options: (type, minimum[, maximum]); the others (tolerance, budgets) are floats >= 0."""


@dataclass
class SizeOptions:
    """Attributes (``size.<name>=<value>`` on the command line):
        out: the sizing folder ("" = ``outputs/size/<date>_<time>``).
        steps: training steps of each trial (0 = half the config's ``train.steps``).
        seeds: runs per trial, seeds ``seed``, ``seed + 1``, ...; the trial's accuracy is their mean.
        metric: ``miou`` (per-image, held-out views), ``ap75`` (matched AP@0.75, held-out) or ``psnr`` (held-out);
            the default by what the model predicts: classes miou, instances ap75, colour only psnr.
        tolerance: a smaller configuration is kept while its metric is at least the reference's minus this
            (absolute: mIoU and AP in [0, 1], PSNR in dB; default 0.02, 0.02 or 0.5).
        min_coverage: fewest source views tried: those that show at least this fraction of a target's pixels
            to two or more of them (the scene measurement).
        depth_margin: the measured depth range is widened by this fraction on each side for near/far.
        knobs: which knobs to size (keys or labels); left out = every knob (an empty list is refused).
        max_parameters, max_flops_per_ray, max_seconds_per_frame, max_memory_mb: budgets the chosen configuration
            must meet (0 = none).
        overwrite: replace a sizing of another request in ``out``.
    """

    out: str = ""
    steps: int = 0
    seeds: int = 1
    metric: str = ""
    tolerance: float = -1.0
    min_coverage: float = 0.8
    depth_margin: float = 0.2
    knobs: list[str] = field(default_factory=list)
    max_parameters: float = 0.0
    max_flops_per_ray: float = 0.0
    max_seconds_per_frame: float = 0.0
    max_memory_mb: float = 0.0
    overwrite: bool = False

    def budgets(self) -> dict[str, float]:
        return {name: value for name in ("max_parameters", "max_flops_per_ray", "max_seconds_per_frame", "max_memory_mb")
                if (value := getattr(self, name)) > 0}

    def request(self) -> dict[str, Any]:
        """What a sizing folder's results depend on (not where it is or whether it may be replaced)."""
        data = asdict(self)
        data.pop("out")
        data.pop("overwrite")
        return data


def _number(key: str, text: str, kind: type, minimum: float, maximum: float = math.inf) -> Any:
    try:
        value = kind(text)
    except ValueError:
        value = None
    if value is None or not math.isfinite(float(value)) or not minimum <= value <= maximum:
        bound = f"in [{minimum}, {maximum}]" if maximum != math.inf else f">= {minimum}"
        raise ConfigError(f"size.{key}={text!r}: expected {'an integer' if kind is int else 'a number'} {bound}")
    return value


def parse_size_options(argv: list[str]) -> tuple[SizeOptions, list[str]]:
    """Split ``size.<name>=<value>`` arguments from the Hydra overrides and check them."""
    options = SizeOptions()
    overrides = []
    known = [name for name in SizeOptions.__dataclass_fields__]
    for argument in argv:
        key, sep, value = argument.partition("=")
        if not key.startswith("size."):
            overrides.append(argument)
            continue
        name = key[len("size."):]
        if name not in known or not sep:
            raise ConfigError(f"{argument!r}: unknown size option; known: {', '.join('size.' + k for k in known)}")
        if name == "out":
            options.out = value
        elif name == "metric":
            if value not in METRICS:
                raise ConfigError(f"size.metric={value!r}: expected one of {', '.join(METRICS)}")
            options.metric = value
        elif name == "knobs":
            options.knobs = _knobs(value)
        elif name == "overwrite":
            if value.lower() not in ("true", "false"):
                raise ConfigError(f"size.overwrite={value!r}: expected true or false")
            options.overwrite = value.lower() == "true"
        else:
            setattr(options, name, _number(name, value, *NUMBERS.get(name, (float, 0.0))))
    return options, overrides


def _knobs(text: str) -> list[str]:
    """``size.knobs``: the knobs declared by the registered families and parts, by key or label."""
    knobs = known_knobs()
    names = [n.strip() for n in text.strip("[]").split(",") if n.strip()]
    if not names:
        raise ConfigError(f"size.knobs={text!r}: expected at least one knob of {', '.join(k.key for k in knobs)} "
                          "(leave size.knobs out to size every knob)")
    by_name = {k.key: k.key for k in knobs} | {k.label.replace(" ", "_"): k.key for k in knobs}
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise ConfigError(f"size.knobs: unknown knob {unknown[0]!r}; known: {', '.join(k.key for k in knobs)} "
                          f"(or {', '.join(k.label.replace(' ', '_') for k in knobs)})")
    return [by_name[n] for n in names]


def check_eval_splits(metric: str, splits: list[str]) -> None:
    """Refuse ``eval.splits`` without the split every trial is compared on (before anything is written or trained)."""
    label = METRICS[metric][0]
    needed = next(split for split, name in SPLIT_LABELS.items() if name == label)
    if needed not in splits:
        raise ConfigError(f"eval.splits=[{','.join(splits)}]: size compares trials by {metric} on the held-out views "
                          f"of the training scenes; expected eval.splits to contain {needed!r} "
                          f"(e.g. eval.splits=[{','.join([needed, *splits])}], or leave eval.splits out)")


def resolve_metric(options: SizeOptions, predicts: str | None) -> tuple[str, float]:
    """The selection metric and tolerance, defaulted from what the model predicts (``classes``, ``instances`` or None:
    colour only); a metric of predictions the model does not make is refused."""
    metric = options.metric or PREDICTS_METRIC.get(predicts or "", "psnr")
    made = PREDICTS_METRIC.get(predicts or "")
    if metric != "psnr" and metric != made:
        what = {"miou": "class scores (a class head, +head=..., or label rendering)",
                "ap75": "instance slots (+head=instance, or an instance family)"}[metric]
        have = f"model predicts {predicts}" if predicts else "model predicts colour only"
        raise ConfigError(f"size.metric={metric} needs a model with {what}; this {have}: use size.metric="
                          f"{made or 'psnr'}")
    tolerance = options.tolerance if options.tolerance >= 0 else DEFAULT_TOLERANCE[metric]
    return metric, tolerance
