"""The descent ``size`` makes: turn one knob down a level at a time while accuracy stays within the tolerance.

From the reference (the configuration asked for, on the scene's measured bounds), knobs are tried in order of the
FLOPs per ray their first level saves. A level is kept when its short training run scores within ``tolerance`` of the
reference; the first level that does not ends that knob, and the next knob starts from everything kept so far, so
every kept configuration was itself trained and measured, the combination included.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.tools.sizing.costs import StaticCost
from gpnerf_core.tools.sizing.knobs import label_of


@dataclass
class Trial:
    """One configuration tried.

    Attributes:
        name: ``reference`` or the change it made (``coarse samples 18``).
        changes: knob key -> value, everything that differs from the reference.
        cost: parameters and FLOPs per ray.
        accuracy: the selection metric, mean over seeds (None when its runs failed).
        measured: per-run figures (``{metric: mean}``: held-out and unseen accuracy, rays/s, s/frame, memory).
        error: why its runs failed.
        kept: whether the descent kept it (within tolerance).
    """

    name: str
    changes: dict[str, int]
    cost: StaticCost
    accuracy: float | None = None
    measured: dict[str, float] = field(default_factory=dict)
    runs: list[str] = field(default_factory=list)
    error: str | None = None
    kept: bool = False


UNBUILT = StaticCost(parameters=0, flops_per_ray=0.0, rays=0)
"""The cost recorded for a configuration that could not be built (it is never kept, so never chosen)."""


def change_name(key: str, value: int) -> str:
    return f"{label_of(key)} {value}"


def describe(changes: dict[str, int]) -> str:
    """Everything a configuration changes from the reference (``fine samples 0, semantic width 8``)."""
    return ", ".join(change_name(k, v) for k, v in changes.items()) or "the reference"


def buildable_cost(cost_of: Callable[[dict[str, int]], StaticCost], changes: dict[str, int]) -> StaticCost | str:
    """The cost of ``changes``, or why that configuration cannot be built (a width another width must divide)."""
    try:
        return cost_of(changes)
    except GpnerfError as exc:
        return str(exc)


def knob_order(levels: dict[str, tuple[int, list[int]]], cost_of: Callable[[dict[str, int]], StaticCost]) -> list[str]:
    """Knobs by the FLOPs per ray (then parameters) their first buildable level saves from the reference, most first;
    a knob with no buildable level on its own goes last."""
    reference = cost_of({})
    savings = {}
    for key, (_, smaller) in levels.items():
        savings[key] = (-1.0, -1.0)
        for value in smaller:
            cost = buildable_cost(cost_of, {key: value})
            if isinstance(cost, StaticCost):
                savings[key] = (reference.flops_per_ray - cost.flops_per_ray, reference.parameters - cost.parameters)
                break
    return sorted(levels, key=lambda key: savings[key], reverse=True)


def descend(
    levels: dict[str, tuple[int, list[int]]],
    order: list[str],
    cost_of: Callable[[dict[str, int]], StaticCost],
    train: Callable[[Trial], None],
    tolerance: float,
    on_trial: Callable[[Trial, Trial], None] | None = None,
) -> list[Trial]:
    """Train the reference, then each knob's levels in ``order`` on top of what was kept.

    Args:
        train: fills a trial's ``accuracy``, ``measured``, ``runs`` (or ``error``) by training it.
        on_trial: called with (trial, reference) after each trial is trained and judged.

    Returns:
        every trial, the reference first. The reference failing raises.
    """
    reference = Trial("reference", {}, cost_of({}))
    train(reference)
    if reference.accuracy is None:
        raise ReferenceFailed(reference.error or "no accuracy")
    reference.kept = True
    if on_trial:
        on_trial(reference, reference)
    trials = [reference]
    kept: dict[str, int] = {}
    for key in order:
        for value in levels[key][1]:
            changes = {**kept, key: value}
            cost = buildable_cost(cost_of, changes)
            if not isinstance(cost, StaticCost):  # not a score below tolerance: the next level may build
                trials.append(Trial(change_name(key, value), changes, UNBUILT, error=f"cannot be built: {cost}"))
                if on_trial:
                    on_trial(trials[-1], reference)
                continue
            trial = Trial(change_name(key, value), changes, cost)
            train(trial)
            trial.kept = trial.accuracy is not None and trial.accuracy >= reference.accuracy - tolerance
            trials.append(trial)
            if on_trial:
                on_trial(trial, reference)
            if not trial.kept:
                break
            kept = changes
    return trials


class ReferenceFailed(Exception):
    """The reference configuration's training failed: there is nothing to size against."""


BUDGETS: dict[str, tuple[str, str]] = {
    "max_parameters": ("parameters", ""),
    "max_flops_per_ray": ("FLOPs per ray", ""),
    "max_seconds_per_frame": ("seconds per frame", " s"),
    "max_memory_mb": ("peak memory", " MB"),
}
"""Budget option -> (what it bounds, unit)."""


def budget_value(trial: Trial, budget: str) -> float | None:
    if budget == "max_parameters":
        return float(trial.cost.parameters)
    if budget == "max_flops_per_ray":
        return trial.cost.flops_per_ray
    if budget == "max_seconds_per_frame":
        return trial.measured.get("seconds_per_frame")
    return trial.measured.get("peak_memory_mb")


def meets(trial: Trial, budgets: dict[str, float]) -> list[str]:
    """The budgets ``trial`` exceeds (a budget it has no figure for counts as exceeded)."""
    failed = []
    for budget, limit in budgets.items():
        value = budget_value(trial, budget)
        if value is None or value > limit:
            failed.append(budget)
    return failed


def choose(trials: list[Trial], budgets: dict[str, float]) -> tuple[Trial | None, str | None]:
    """The cheapest kept trial (FLOPs per ray, then parameters) within every budget, or why there is none."""
    kept = [t for t in trials if t.kept]
    fitting = [t for t in kept if not meets(t, budgets)]
    if fitting:
        return min(fitting, key=lambda t: (t.cost.flops_per_ray, t.cost.parameters)), None
    reasons = []
    for budget, limit in budgets.items():
        values = [v for t in kept if (v := budget_value(t, budget)) is not None]
        if values and min(values) <= limit:
            continue
        what, unit = BUDGETS[budget]
        best = f"the least within tolerance is {format_figure(min(values))}{unit}" if values else "nothing measured it"
        reasons.append(f"size.{budget}={format_option(limit)}: no configuration within the tolerance meets it ({what}: {best})")
    if not reasons:
        reasons.append("no configuration within the tolerance meets every budget at once: "
                       + ", ".join(f"size.{b}={format_option(v)}" for b, v in budgets.items()))
    return None, "; ".join(reasons)


def format_figure(value: float) -> str:
    """A figure for a message: thousands separated from 10,000 on, else 4 significant digits."""
    return f"{value:,.0f}" if abs(value) >= 1e4 else f"{value:.4g}"


def format_option(value: float) -> str:
    """A budget as the user would type it (``2000000``, ``0.5``)."""
    return f"{value:.12g}"


def refuse_unreachable_budgets(budgets: dict[str, float], levels: dict[str, tuple[int, list[int]]],
                                cost_of: Any) -> None:
    """Parameter and FLOP budgets are known before training: refuse one not even every knob at its lowest meets."""
    static = {b: v for b, v in budgets.items() if b in ("max_parameters", "max_flops_per_ray")}
    if not static:
        return
    smallest = {key: smaller[-1] for key, (_, smaller) in levels.items()}
    cost = buildable_cost(cost_of, smallest)
    if not isinstance(cost, StaticCost):
        return  # the smallest corner cannot be built; the descent reports the budgets at the end
    trial = Trial("smallest", smallest, cost)
    failed = meets(trial, static)
    if failed:
        reached = ", ".join(f"{label_of(k)} {v}" for k, v in smallest.items()) or "the reference (no knob to turn)"
        values = {"max_parameters": f"{cost.parameters:,} parameters",
                  "max_flops_per_ray": f"{format_figure(cost.flops_per_ray)} FLOPs per ray"}
        raise ConfigError(
            "; ".join(f"size.{b}={format_option(static[b])}: no configuration the search can reach meets it "
                      f"(the smallest, {reached}, has {values[b]})" for b in failed)
        )
