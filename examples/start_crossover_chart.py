"""The crossover chart and table of ``examples/start_crossover.py``'s work folders (docs/results.md, "From the first
second to the scene's own model").

    python examples/start_crossover_chart.py WORK [WORK ...] [--out docs/images/start_crossover.png] \
        [--seconds 300] [--at 30,60,120,240] [--metric miou]

Each WORK is one scene and seed (its ``curves.json``); folders of one scene (the same ``scene`` in their curves) are
one panel, their seeds averaged. Each row is drawn as its mean over seeds against per-scene training seconds with a
band of +- one standard deviation, from its first point to the last second every seed reached (a seed's curve is
interpolated linearly between its evaluations: a model between two evaluations is not measured). A zero-shot row is
its value at 0 s, drawn as a dotted line across the panel (it trains nothing on the scene). Prints, per scene, a
markdown table: each row's value at 0 s and at each ``--at`` second (mean +- std over seeds; "-" where a row has not
reached that second), at its last point, and the seeds. The PNG is written atomically.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
from pathlib import Path

LABELS = {
    "zero_shot": "GP-NeRF zero-shot",
    "zero_shot_mvsplat": "MVSplat + U-Net head zero-shot",
    "finetune": "GP-NeRF fine-tuned",
    "grid": "Semantic-NeRF (grid)",
    "splat_points": "Semantic 3DGS from points",
    "splat_gpnerf": "Semantic 3DGS started from GP-NeRF",
    "splat_mvsplat": "Semantic 3DGS started from MVSplat + head",
    "splat_points_gpnerf": "Semantic 3DGS from points, GP-NeRF's semantics",
}
"""Each row's name on the chart and in the table, in drawing order."""


def value_at(points: list[dict], seconds: float, metric: str) -> float | None:
    """The curve's ``metric`` at ``seconds``, linear between the evaluations around it; None outside its points."""
    known = [(p["seconds"], p[metric]) for p in points if p.get(metric) is not None]
    if not known or seconds < known[0][0] - 1e-9 or seconds > known[-1][0] + 1e-9:
        return None
    for (s0, v0), (s1, v1) in zip(known, known[1:]):
        if s0 <= seconds <= s1:
            return v0 if s1 == s0 else v0 + (v1 - v0) * (seconds - s0) / (s1 - s0)
    return known[-1][1]


def mean_std(values: list[float]) -> tuple[float, float]:
    mean = sum(values) / len(values)
    return mean, math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1)) if len(values) > 1 else 0.0


def scenes_of(folders: list[Path]) -> dict[str, list[dict]]:
    """``{scene: [curves of each seed]}`` in the order the folders name them."""
    scenes: dict[str, list[dict]] = {}
    for folder in folders:
        curves = json.loads((folder / "curves.json").read_text())
        scenes.setdefault(curves["scene"], []).append(curves)
    return scenes


def summary(seeds: list[dict], row: str, seconds: float, metric: str) -> tuple[float, float] | None:
    """Mean and std over the seeds that have ``row`` at ``seconds`` (zero-shot: its one value); None if any lacks it."""
    values = []
    for curves in seeds:
        points = curves.get(row)
        if not points:
            return None
        value = points[0][metric] if row.startswith("zero_shot") else value_at(points, seconds, metric)
        if value is None:
            return None
        values.append(value)
    return mean_std(values)


def table(scene: str, seeds: list[dict], at: list[float], metric: str) -> str:
    header = ["model", "0 s", *(f"{t:g} s" for t in at), "last point (s)", "seeds"]
    lines = [f"**{scene}** ({metric})", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row, label in LABELS.items():
        if not all(curves.get(row) for curves in seeds):
            continue
        cells = [label]
        for t in [0.0, *at]:
            got = summary(seeds, row, t, metric)
            cells.append("-" if got is None else f"{got[0]:.3f} +- {got[1]:.3f}")
        lasts = [curves[row][-1] for curves in seeds]
        value = mean_std([p[metric] for p in lasts if p.get(metric) is not None] or [float("nan")])
        cells.append(f"{value[0]:.3f} +- {value[1]:.3f} ({mean_std([p['seconds'] for p in lasts])[0]:.0f})")
        cells.append(",".join(str(curves["seed"]) for curves in seeds))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def draw(scenes: dict[str, list[dict]], out: Path, limit: float, metric: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(scenes), figsize=(5.2 * len(scenes), 4.2), squeeze=False)
    colours = dict(zip(LABELS, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for axis, (scene, seeds) in zip(axes[0], scenes.items()):
        for row, label in LABELS.items():
            if not all(curves.get(row) for curves in seeds):
                continue
            if row.startswith("zero_shot"):
                mean, std = summary(seeds, row, 0.0, metric)
                axis.axhline(mean, color=colours[row], linestyle=":", label=f"{label} ({mean:.3f})")
                axis.plot([0], [mean], "o", color=colours[row])
                continue
            start = max(curves[row][0]["seconds"] for curves in seeds)
            end = min(limit, min(curves[row][-1]["seconds"] for curves in seeds))
            grid = [start + (end - start) * k / 200 for k in range(201)] if end > start else [start]
            stats = [summary(seeds, row, t, metric) for t in grid]
            xs = [t for t, s in zip(grid, stats) if s is not None]
            means = [s[0] for s in stats if s is not None]
            stds = [s[1] for s in stats if s is not None]
            axis.plot(xs, means, color=colours[row], label=label)
            axis.fill_between(xs, [m - s for m, s in zip(means, stds)], [m + s for m, s in zip(means, stds)],
                              color=colours[row], alpha=0.2, linewidth=0)
        axis.set_xlim(0, limit)
        axis.set_title(f"{scene} (seeds {','.join(str(c['seed']) for c in seeds)})", fontsize=10)
        axis.set_xlabel("per-scene training seconds (a started model's start included)")
        axis.set_ylabel("per-image mIoU, held-out frames" if metric == "miou" else metric)
        axis.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(suffix=".png", dir=out.parent)
    os.close(handle)
    try:
        fig.savefig(temporary, dpi=110)
        os.replace(temporary, out)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("work", type=Path, nargs="+")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--seconds", type=float, default=300.0)
    parser.add_argument("--at", default="30,60,120,240")
    parser.add_argument("--metric", default="miou", choices=("miou", "miou_dataset", "psnr"))
    args = parser.parse_args()
    scenes = scenes_of(args.work)
    at = [float(t) for t in args.at.split(",") if t]
    for scene, seeds in scenes.items():
        print(table(scene, seeds, at, args.metric), end="\n\n")
    if args.out is not None:
        draw(scenes, args.out, args.seconds, args.metric)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
