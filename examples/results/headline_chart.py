"""The headline chart of docs/results.md, drawn from the committed table ``examples/results/headline.csv``:

    python examples/results/headline_chart.py [--csv examples/results/headline.csv] \
        [--out docs/images/results_headline.png]

One figure row per ``setting`` (in the order the CSV first names them: generalized, per scene), two panels per row:
accuracy against seconds per rendered frame and against training seconds, both on a log x axis. Error bars are the
standard deviation over the row's seeds (x error bars where the CSV gives one for the cost too); each method is
labelled by its name. A row without a cost on a panel is drawn as a horizontal line (its accuracy) with a band of
+- std, labelled "no cost figure"; a row without an accuracy is not drawn and is listed under the figure with its note.
Markers: one shape per ``metric`` (mIoU, AP@0.75, ...), filled for the first ``split`` the CSV names and open for the
next; colours: one per ``method``. Nothing here names a method: a row added to the CSV (MVSplat, say) is drawn.

Columns: method, setting, split, metric, mean, std, s_per_frame, s_per_frame_std, train_s, train_s_std, seeds, steps,
source (the docs/results_detail.md section the figures come from), note. Empty cells are figures not measured.
The PNG is written atomically (a temporary file in the same folder, then ``os.replace``).
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CSV = ROOT / "examples" / "results" / "headline.csv"
OUT = ROOT / "docs" / "images" / "results_headline.png"
COSTS = (("s_per_frame", "seconds per rendered frame (log)"), ("train_s", "training seconds (log)"))
MARKERS = ("o", "^", "s", "D", "v", "P", "X")
FILLS = ("full", "none", "left", "bottom")
LINES = ("-", "--", ":", "-.")


def number(text: str | None) -> float | None:
    text = (text or "").strip()
    return float(text) if text else None


def read_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        rows = [{k: (v or "").strip() for k, v in row.items()} for row in csv.DictReader(handle)]
    needed = {"method", "setting", "split", "metric", "mean", "std", "s_per_frame", "train_s"}
    missing = needed - set(rows[0] if rows else needed)
    if missing:
        raise SystemExit(f"{path}: missing columns {sorted(missing)}")
    return rows


def leading_digit(value: float) -> int:
    return round(value / 10 ** math.floor(math.log10(value))) if value > 0 else 0


def in_order(values) -> list[str]:
    return list(dict.fromkeys(values))


def label_points(fig, ax, pending, cost, colour, fixed, lines) -> None:
    """Each method's name beside its points, at the first of a few places that overlaps no marker and no label."""
    from matplotlib.transforms import Bbox

    renderer = fig.canvas.get_renderer()
    pad = 7.0
    taken = [a.get_window_extent(renderer).expanded(1.02, 1.1) for a in fixed]
    if ax.get_legend() is not None:
        taken.append(ax.get_legend().get_window_extent(renderer))
    for y in lines:  # every line drawn for a row without a cost is an obstacle
        _, level = ax.transData.transform((1.0, y))
        taken.append(Bbox([[ax.bbox.x0, level - 2], [ax.bbox.x1, level + 2]]))
    for _, points in pending:  # every marker is an obstacle
        for r in points:
            x, y = ax.transData.transform((number(r[cost]), number(r["mean"])))
            taken.append(Bbox([[x - pad, y - pad], [x + pad, y + pad]]))
    for method, points in pending:
        top = max(points, key=lambda r: number(r["mean"]))
        low = min(points, key=lambda r: number(r["mean"]))
        tries = [(top, (8, 5), "left"), (low, (8, -13), "left"), (top, (-8, 5), "right"), (low, (-8, -13), "right"),
                 (top, (8, 16), "left"), (low, (8, -24), "left"), (top, (-8, 16), "right"), (low, (-8, -24), "right")]
        chosen = None
        for anchor, offset, ha in tries:
            text = ax.annotate(method, (number(anchor[cost]), number(anchor["mean"])), xytext=offset,
                               textcoords="offset points", ha=ha, fontsize=9, color=colour[method])
            box = text.get_window_extent(renderer)
            inside = ax.bbox.containsx(box.x0) and ax.bbox.containsx(box.x1) and ax.bbox.containsy(box.y1) \
                and ax.bbox.containsy(box.y0)
            if inside and not any(box.overlaps(other) for other in taken):
                chosen = text
                break
            text.remove()
        if chosen is None:  # every place overlaps: the first one
            anchor, offset, ha = tries[0]
            chosen = ax.annotate(method, (number(anchor[cost]), number(anchor["mean"])), xytext=offset,
                                 textcoords="offset points", ha=ha, fontsize=9, color=colour[method])
        taken.append(chosen.get_window_extent(renderer))


def draw(rows: list[dict[str, str]], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter

    settings = in_order(r["setting"] for r in rows)
    methods = in_order(r["method"] for r in rows)
    metrics = in_order(r["metric"] for r in rows)
    splits = in_order(r["split"] for r in rows)
    palette = list(plt.get_cmap("tab10").colors) + list(plt.get_cmap("Dark2").colors)
    colour = {m: palette[i % len(palette)] for i, m in enumerate(methods)}
    marker = {m: MARKERS[i % len(MARKERS)] for i, m in enumerate(metrics)}
    fill = {s: FILLS[min(i, len(FILLS) - 1)] for i, s in enumerate(splits)}
    line = {s: LINES[min(i, len(LINES) - 1)] for i, s in enumerate(splits)}

    drawn = [r for r in rows if number(r["mean"]) is not None]
    not_drawn = in_order(f"{r['method']} ({r['setting']}): {r.get('note') or 'no accuracy figure'}"
                         for r in rows if number(r["mean"]) is None)
    to_label: list = []
    fig, axes = plt.subplots(len(settings), len(COSTS), figsize=(13, 4.8 * len(settings)), squeeze=False)
    for i, setting in enumerate(settings):
        here = [r for r in drawn if r["setting"] == setting]
        ylabel = " / ".join(in_order(r["metric"] for r in here)) or "accuracy"
        for j, (cost, xlabel) in enumerate(COSTS):
            ax = axes[i][j]
            placed = [r for r in here if number(r.get(cost)) is not None]
            lines = [r for r in here if number(r.get(cost)) is None]
            fixed: list = []
            labelled: set[str] = set()
            pending: list[tuple[str, list[dict[str, str]]]] = []
            for method in in_order(r["method"] for r in placed):
                points = sorted((r for r in placed if r["method"] == method), key=lambda r: splits.index(r["split"]))
                if len(points) > 1:  # the same model's splits at the same cost: joined
                    ax.plot([number(r[cost]) for r in points], [number(r["mean"]) for r in points],
                            color=colour[method], lw=0.8, alpha=0.6, zorder=1)
                for r in points:
                    x, y = number(r[cost]), number(r["mean"])
                    ax.errorbar(x, y, yerr=number(r["std"]) or 0.0, xerr=number(r.get(f"{cost}_std")),
                                fmt=marker[r["metric"]], color=colour[method], fillstyle=fill[r["split"]],
                                markerfacecolor=colour[method] if fill[r["split"]] == "full" else "white",
                                markersize=8, capsize=3, lw=1.2, zorder=3)
                pending.append((method, points))
                labelled.add(method)
            for r in lines:
                y, std = number(r["mean"]), number(r["std"]) or 0.0
                ax.axhline(y, color=colour[r["method"]], ls=line[r["split"]], lw=1.1, alpha=0.8, zorder=2)
                if std:
                    ax.axhspan(y - std, y + std, color=colour[r["method"]], alpha=0.08, lw=0, zorder=0)
                if r["method"] not in labelled:
                    fixed.append(ax.annotate(f"{r['method']} (no cost figure)", (1.0, y),
                                             xycoords=("axes fraction", "data"), xytext=(-4, 3),
                                             textcoords="offset points", ha="right", fontsize=8,
                                             color=colour[r["method"]]))
                    labelled.add(r["method"])
            if placed:
                ax.set_xscale("log")
                xs = [number(r[cost]) for r in placed]
                ax.set_xlim(min(xs) / 1.8, max(xs) * 2.2)
                plain = FuncFormatter(lambda v, _: f"{v:g}")
                ax.xaxis.set_major_formatter(plain)
                ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if leading_digit(v) in (2, 5) else ""))
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
            ax.set_title(f"{setting}: {ylabel} against {xlabel.replace(' (log)', '')}", fontsize=10)
            ax.grid(True, which="both", alpha=0.25)
            ax.set_ylim(bottom=max(0.0, min(number(r["mean"]) - (number(r["std"]) or 0) for r in here) - 0.05)
                        if here else None)
            to_label.append((ax, pending, cost, fixed, [number(r["mean"]) for r in lines]))
            if j == 0:
                keys = in_order((r["metric"], r["split"]) for r in here)
                handles = [Line2D([], [], ls="none", marker=marker[m], color="0.3", fillstyle=fill[s],
                                  markerfacecolor="0.3" if fill[s] == "full" else "white", label=f"{m}, {s}")
                           for m, s in keys]
                handles += [Line2D([], [], ls=line[s], color="0.3", label=f"{s}, no cost figure")
                            for s in in_order(r["split"] for r in here if any(number(r.get(c)) is None
                                                                               for c, _ in COSTS))]
                ax.legend(handles=handles, fontsize=8, loc="lower left", framealpha=0.85)
    fig.suptitle("Every method: accuracy against cost (mean +- std over seeds; docs/results.md, figures from "
                 "docs/results_detail.md)", fontsize=11)
    footer = "\n".join(f"Not drawn: {text}" for text in not_drawn)
    fig.tight_layout(rect=(0, 0.03 * max(1, len(not_drawn)) if not_drawn else 0, 1, 0.97))
    if footer:
        fig.text(0.01, 0.005, footer, fontsize=8, va="bottom", ha="left", wrap=True)
    for ax, pending, cost, fixed, levels in to_label:  # after the layout: names go where they overlap nothing
        label_points(fig, ax, pending, cost, colour, fixed, levels)

    out.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=out.suffix, dir=out.parent)
    os.close(handle)
    try:
        fig.savefig(temporary, dpi=120)
        os.replace(temporary, out)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    finally:
        plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--csv", type=Path, default=CSV, help=f"the table (default {CSV.relative_to(ROOT)})")
    parser.add_argument("--out", type=Path, default=OUT, help=f"the PNG (default {OUT.relative_to(ROOT)})")
    args = parser.parse_args(argv)
    rows = read_rows(args.csv)
    print(draw(rows, args.out))


if __name__ == "__main__":
    main()
