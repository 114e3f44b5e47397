"""Speed against accuracy: ``report <runs> --chart DIR`` draws every method's accuracy against its costs.

One point per method (runs differing only by seed are one method: the point is their mean, the error bars their sample
standard deviations), one panel per (accuracy, cost) pair that some run measured, and in each panel the Pareto front:
the methods no other method beats on both axes. The CSV behind the chart and the front's members are written beside it.
"""

from __future__ import annotations

import csv
import io
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from gpnerf_core.runtime.io import atomic_write_bytes, atomic_write_text


@dataclass(frozen=True)
class Axis:
    """One quantity read from a run's ``metrics.json``.

    Attributes:
        name: column and axis label; unit: shown on the axis.
        read: ``metrics -> value`` (None when the run did not measure it).
        higher_is_better: accuracy, throughput (True) or cost (False), for the Pareto front.
    """

    name: str
    unit: str
    read: Callable[[dict[str, Any]], Any]
    higher_is_better: bool


def _eval(split: str, key: str) -> Callable[[dict[str, Any]], Any]:
    return lambda metrics: metrics.get("eval", {}).get(split, {}).get(key)


def _first_split_timing(key: str) -> Callable[[dict[str, Any]], Any]:
    def read(metrics: dict[str, Any]) -> Any:
        splits = metrics.get("eval", {})
        for split in ("train_heldout", "unseen"):
            value = splits.get(split, {}).get("timing", {}).get(key)
            if value is not None:
                return value
        return None

    return read


CURVE_KEYS = {
    "mIoU held-out": ("train_heldout", "miou/image_mean_present"),
    "mIoU unseen": ("unseen", "miou/image_mean_present"),
    "PSNR held-out": ("train_heldout", "psnr/clamped"),
    "AP@0.75 held-out": ("train_heldout", "instance/ap_matched@0.75"),
}
"""Where each accuracy axis is in an ``eval_curve`` entry of ``metrics.json``."""

ACCURACY = (
    Axis("mIoU held-out", "per-image mIoU", _eval("train_heldout", "miou/image_mean_present"), True),
    Axis("mIoU unseen", "per-image mIoU", _eval("unseen", "miou/image_mean_present"), True),
    Axis("PSNR held-out", "dB", _eval("train_heldout", "psnr/clamped"), True),
    Axis("AP@0.75 held-out", "matched AP", _eval("train_heldout", "instance/ap_matched@0.75"), True),
)
COSTS = (
    Axis("training time", "s", lambda m: m.get("train", {}).get("seconds"), False),
    Axis("training throughput", "rays/s", lambda m: m.get("train", {}).get("rays_per_second"), True),
    Axis("rendering", "s per frame", _first_split_timing("seconds_per_frame"), False),
    Axis("parameters", "millions", lambda m: _millions(m.get("parameters", {}).get("total")), False),
    Axis("FLOPs per ray", "millions", lambda m: _millions(m.get("flops_per_ray")), False),
    Axis("peak memory", "MB", _first_split_timing("peak_memory_mb"), False),
)


def _millions(value: Any) -> float | None:
    return None if value is None else float(value) / 1e6


@dataclass(frozen=True)
class Point:
    """One method on one axis: mean, sample standard deviation (0 for one run) and number of runs."""

    mean: float
    std: float
    n: int


def point(values: list[float]) -> Point | None:
    if not values:
        return None
    return Point(statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0, len(values))


@dataclass(frozen=True)
class Method:
    """A group of runs (same config up to the seed) and its points on every axis it has.

    ``curves``: accuracy axis -> ``[(training seconds, Point)]`` over the runs' ``eval_curve`` steps (``eval.every_steps``),
    taken at the steps every run of the group evaluated.
    """

    label: str
    seeds: list[Any]
    points: dict[str, Point]
    curves: dict[str, list[tuple[Point, Point]]]


def curves_of(runs: list[Any]) -> dict[str, list[tuple[Point, Point]]]:
    """Mean and spread over runs of (training seconds, accuracy) at each step all runs evaluated."""
    by_step: list[dict[int, dict[str, Any]]] = [
        {int(entry["step"]): entry for entry in run.metrics.get("eval_curve") or []} for run in runs
    ]
    steps = sorted(set.intersection(*(set(d) for d in by_step))) if by_step else []
    curves: dict[str, list[tuple[Point, Point]]] = {}
    for name, (split, key) in CURVE_KEYS.items():
        line = []
        for step in steps:
            entries = [d[step] for d in by_step]
            values = [e.get(split, {}).get(key) for e in entries]
            if any(v is None for v in values):
                continue
            line.append((point([float(e["train_seconds"]) for e in entries]), point([float(v) for v in values])))
        if len(line) > 1:
            curves[name] = line
    return curves


def methods_from_groups(groups: list[Any], labels: list[str]) -> list[Method]:
    """``report.RowGroup`` s and their legend entries (failed runs left out) -> methods with a point on every axis
    some run measured."""
    out = []
    for group, label in zip(groups, labels):
        runs = [run for run in group.runs if run.error is None]
        if not runs:
            continue
        points = {}
        for axis in ACCURACY + COSTS:
            values = [float(v) for run in runs if (v := axis.read(run.metrics)) is not None]
            if (p := point(values)) is not None:
                points[axis.name] = p
        out.append(Method(label, [run.config.get("seed", "?") for run in runs], points, curves_of(runs)))
    return out


def pareto_front(methods: list[Method], accuracy: Axis, cost: Axis) -> list[Method]:
    """Methods on both axes that no other method matches or beats on both and beats on one, ordered by cost."""
    sign = 1.0 if cost.higher_is_better else -1.0
    placed = [m for m in methods if accuracy.name in m.points and cost.name in m.points]

    def beats(a: Method, b: Method) -> bool:
        ya, yb = a.points[accuracy.name].mean, b.points[accuracy.name].mean
        xa, xb = sign * a.points[cost.name].mean, sign * b.points[cost.name].mean
        return ya >= yb and xa >= xb and (ya > yb or xa > xb)

    front = [m for m in placed if not any(beats(other, m) for other in placed if other is not m)]
    return sorted(front, key=lambda m: m.points[cost.name].mean)


HEADLINE = ("mIoU held-out", "rendering")
"""The panel a reader sees first: held-out accuracy against the seconds a frame takes to render."""


def draw(methods: list[Method], folder: Path) -> dict[str, list[str]]:
    """Write ``speed_accuracy.png``, ``speed_accuracy.csv`` and ``pareto.txt`` into ``folder``.

    ``speed_accuracy.png`` leads with the headline panel (``HEADLINE``, wider) above the grid of every (accuracy,
    cost) pair; the headline panel alone is also ``headline.png``. Neither is drawn without a method on both of its
    axes.

    Returns:
        ``{"<accuracy> vs <cost>": [front members' labels]}`` for every panel drawn. With ``eval_curve`` s in the
        runs, ``accuracy_vs_time.png`` too.
    """
    accuracies = [a for a in ACCURACY if any(a.name in m.points for m in methods)]
    costs = [c for c in COSTS if any(c.name in m.points for m in methods)]
    by_name = {axis.name: axis for axis in ACCURACY + COSTS}
    headline = [by_name[name] for name in HEADLINE]
    has_headline = any(all(a.name in m.points for a in headline) for m in methods)
    fronts: dict[str, list[str]] = {}
    width = max(3.4 * max(len(costs), 1), 7.0)
    grid_height = 2.9 * max(len(accuracies), 1)
    head_height = 3.6 if has_headline else 0.0
    figure = Figure(figsize=(width, grid_height + head_height + 0.8), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    if has_headline:
        top, bottom = figure.subfigures(2, 1, height_ratios=[head_height, grid_height + 0.8])
        _panel(top.add_subplot(1, 1, 1), methods, headline[0], headline[1], title=True)
    else:
        bottom = figure
    for row, accuracy in enumerate(accuracies):
        for column, cost in enumerate(costs):
            axis = bottom.add_subplot(len(accuracies), len(costs), row * len(costs) + column + 1)
            front = _panel(axis, methods, accuracy, cost)
            if front:
                fronts[f"{accuracy.name} vs {cost.name}"] = [m.label for m in front]
    _legend(figure, figure.axes)
    atomic_write_bytes(folder / "speed_accuracy.png", _png(figure))
    if has_headline:
        alone = Figure(figsize=(7.0, 4.6), dpi=110, layout="constrained")
        FigureCanvasAgg(alone)
        axis = alone.add_subplot(1, 1, 1)
        _panel(axis, methods, headline[0], headline[1], title=True)
        _legend(alone, [axis])
        atomic_write_bytes(folder / "headline.png", _png(alone))
    atomic_write_text(folder / "speed_accuracy.csv", _csv(methods, accuracies + costs))
    lines = [f"{panel}: {', '.join(names)}\n" for panel, names in fronts.items()]
    atomic_write_text(folder / "pareto.txt", "".join(lines))
    if any(m.curves for m in methods):
        _draw_curves(methods, folder / "accuracy_vs_time.png")
    return fronts


def _panel(axis: Any, methods: list[Method], accuracy: Axis, cost: Axis, title: bool = False) -> list[Method]:
    """One (accuracy, cost) panel: every method's mean with its seed spread, the Pareto front dashed."""
    markers = "os^Dv<>pP*Xh"
    for index, method in enumerate(methods):
        y, x = method.points.get(accuracy.name), method.points.get(cost.name)
        if x is None or y is None:
            continue
        axis.errorbar(x.mean, y.mean, xerr=x.std or None, yerr=y.std or None, fmt=markers[index % len(markers)],
                      color=f"C{index % 10}", capsize=2, markersize=6 if title else 5, label=method.label)
    front = pareto_front(methods, accuracy, cost)
    if len(front) > 1:
        axis.plot([m.points[cost.name].mean for m in front], [m.points[accuracy.name].mean for m in front],
                  color="0.4", linestyle="--", linewidth=0.9, zorder=0)
    better = "higher" if cost.higher_is_better else "lower"
    size = 9 if title else 8
    axis.set_xlabel(f"{cost.name} ({cost.unit}), {better} is better", fontsize=size)
    axis.set_ylabel(f"{accuracy.name} ({accuracy.unit})", fontsize=size)
    if title:
        axis.set_title(f"{accuracy.name} against {cost.name}: mean +- std over seeds, dashed: Pareto front",
                       fontsize=9)
    axis.tick_params(labelsize=size - 1)
    axis.grid(True, alpha=0.3)
    return front


def _legend(figure: Any, axes: list[Any]) -> None:
    handles, labels = [], []
    for axis in axes:
        for handle, text in zip(*axis.get_legend_handles_labels()):
            if text not in labels:
                handles.append(handle)
                labels.append(text)
    if handles:
        columns = 1 if max(map(len, labels)) > 48 else min(2, len(labels))
        figure.legend(handles, labels, loc="outside lower center", ncol=columns, fontsize=8,
                      title="method (mean +- std over seeds; dashed: Pareto front)", title_fontsize=8)


def _png(figure: Figure) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


def _draw_curves(methods: list[Method], path: Path) -> None:
    """Accuracy against training seconds, one line per method (mean over seeds, band: +- one standard deviation)."""
    names = [name for name in CURVE_KEYS if any(name in m.curves for m in methods)]
    figure = Figure(figsize=(6.0, 2.8 * len(names) + 0.6), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    for row, name in enumerate(names):
        axis = figure.add_subplot(len(names), 1, row + 1)
        for index, method in enumerate(methods):
            line = method.curves.get(name)
            if not line:
                continue
            xs = [x.mean for x, _ in line]
            ys = [y.mean for _, y in line]
            axis.plot(xs, ys, marker="o", markersize=3, color=f"C{index % 10}", label=method.label)
            if any(y.std for _, y in line):
                axis.fill_between(xs, [y.mean - y.std for _, y in line], [y.mean + y.std for _, y in line],
                                  color=f"C{index % 10}", alpha=0.15, linewidth=0)
        unit = next(a.unit for a in ACCURACY if a.name == name)
        axis.set_xlabel("training time (s)", fontsize=8)
        axis.set_ylabel(f"{name} ({unit})", fontsize=8)
        axis.tick_params(labelsize=7)
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize=7, loc="lower right")
    atomic_write_bytes(path, _png(figure))


def _csv(methods: list[Method], axes: list[Axis]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    header = ["method", "seeds", "n"]
    for axis in axes:
        header += [f"{axis.name} ({axis.unit}) mean", f"{axis.name} std"]
    writer.writerow(header)
    for method in methods:
        row: list[Any] = [method.label, " ".join(map(str, method.seeds)), len(method.seeds)]
        for axis in axes:
            p = method.points.get(axis.name)
            row += ["", ""] if p is None else [f"{p.mean:.6g}", f"{p.std:.6g}"]
        writer.writerow(row)
    return buffer.getvalue()
