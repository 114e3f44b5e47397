"""How each cost grows: ``bench sweep=rays|views|samples|image`` measures one size's GP-NeRF and GNT-only variants
over a range of one quantity and fits the slope of log(cost) against log(quantity).

A slope of 1 is linear growth; the fit is least squares on the log-log points (``fitted_slope``). Each point is
``bench``'s child-process measurement (``measure.run_measurement``), so its peak memory is its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from gpnerf_core.errors import ConfigError


@dataclass(frozen=True)
class Sweep:
    """One swept quantity.

    Attributes:
        name: ``rays``, ``views``, ``samples``, ``image``.
        label: the x axis, with its unit.
        points: ``(x value, overrides)`` in increasing x.
        phases: what is measured at each point (rays per step change training only).
    """

    name: str
    label: str
    points: tuple[tuple[float, tuple[str, ...]], ...]
    phases: tuple[str, ...]


def _samples(total: int) -> tuple[str, ...]:
    """``total`` samples per ray as the paper splits 64: three quarters coarse, one quarter fine."""
    fine = total // 4
    return (f"model.coarse_samples={total - fine}", f"model.fine_samples={fine}")


def _image(height: int, width: int) -> tuple[str, ...]:
    return (f"dataset.height={height}", f"dataset.width={width}")


SWEEPS: dict[str, Sweep] = {
    sweep.name: sweep
    for sweep in (
        Sweep("rays", "rays per training step", tuple((r, (f"train.rays={r}",)) for r in (64, 128, 256, 512, 1024)),
              ("train",)),
        Sweep("views", "source views", tuple((v, (f"model.num_source_views={v}",)) for v in (2, 4, 6, 8, 10)),
              ("train", "render")),
        Sweep("samples", "samples per ray (coarse + fine)", tuple((s, _samples(s)) for s in (16, 32, 64, 128)),
              ("train", "render")),
        Sweep("image", "pixels per image",
              tuple((h * w, _image(h, w)) for h, w in ((96, 128), (144, 192), (192, 256), (240, 320))),
              ("train", "render")),
    )
}


def get_sweep(name: str) -> Sweep:
    if name not in SWEEPS:
        raise ConfigError(f"bench sweep={name!r} is unknown; known sweeps: {', '.join(SWEEPS)}")
    return SWEEPS[name]


COSTS = (
    ("train", "seconds_min", "training step (s)"),
    ("train", "peak_memory_mb", "training peak memory (MiB)"),
    ("render", "seconds_min", "rendering a view (s)"),
    ("render", "peak_memory_mb", "rendering peak memory (MiB)"),
)
"""(phase, key in the measurement, what it is): the costs a sweep fits and draws."""


def fitted_slope(xs: Sequence[float], ys: Sequence[float]) -> float | None:
    """Least-squares slope of log(y) against log(x) over the positive pairs; None with fewer than two."""
    pairs = [(math.log(x), math.log(y)) for x, y in zip(xs, ys) if x and y and x > 0 and y > 0]
    if len(pairs) < 2:
        return None
    mean_x = sum(p[0] for p in pairs) / len(pairs)
    mean_y = sum(p[1] for p in pairs) / len(pairs)
    spread = sum((p[0] - mean_x) ** 2 for p in pairs)
    return sum((p[0] - mean_x) * (p[1] - mean_y) for p in pairs) / spread if spread else None


def rows_of(sweep: Sweep, measured: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """One CSV row per (variant, point): x and every cost (empty where a phase was not measured or failed)."""
    rows = []
    for variant, points in measured.items():
        for (x, _), result in zip(sweep.points, points):
            row: dict[str, Any] = {"variant": variant, sweep.name: x}
            for phase, key, title in COSTS:
                value = result.get(phase, {}).get(key)
                row[title] = value if isinstance(value, (int, float)) else None
            row["error"] = "; ".join(str(result[p]["error"]) for p in result if "error" in result[p]) or None
            rows.append(row)
    return rows


def slopes(sweep: Sweep, rows: list[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """``{variant: {cost title: fitted slope}}``."""
    found: dict[str, dict[str, float | None]] = {}
    for variant in dict.fromkeys(row["variant"] for row in rows):
        mine = [row for row in rows if row["variant"] == variant]
        found[variant] = {title: fitted_slope([r[sweep.name] for r in mine], [r[title] for r in mine])
                          for _, _, title in COSTS}
    return found


def draw(sweep: Sweep, rows: list[dict[str, Any]], path: Path) -> None:
    """One PNG: a log-log panel per cost, GP-NeRF and GNT-only, the fitted slope in the legend."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gpnerf_core.runtime.io import atomic_write_bytes

    fitted = slopes(sweep, rows)
    figure, axes = plt.subplots(1, len(COSTS), figsize=(4.2 * len(COSTS), 3.6))
    for axis, (_, _, title) in zip(axes, COSTS):
        for variant, marker in (("gpnerf", "o-"), ("gnt_only", "s--")):
            points = [(r[sweep.name], r[title]) for r in rows if r["variant"] == variant and r[title]]
            if not points:
                continue
            slope = fitted[variant][title]
            label = f"{'GP-NeRF' if variant == 'gpnerf' else 'GNT-only'} (slope {slope:.2f})" if slope is not None \
                else variant
            axis.plot([p[0] for p in points], [p[1] for p in points], marker, label=label)
        axis.set_xscale("log")
        axis.set_yscale("log")
        xs = [point[0] for point in sweep.points]  # ticks at the measured values: log ranges this short get none
        axis.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        axis.set_xticks(xs, [f"{x:g}" for x in xs], fontsize=8)
        axis.set_xlabel(sweep.label)
        axis.set_title(title, fontsize=10)
        axis.grid(True, which="both", alpha=0.3)
        if axis.lines:
            axis.legend(fontsize=8)
    figure.tight_layout()
    import io

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    plt.close(figure)
    atomic_write_bytes(path, buffer.getvalue())
