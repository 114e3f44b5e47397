"""The stress suite's figures: mean and std over seeds per (method, case, level), when each method fails, which
method degrades least, and one PNG per case (metric against level, one line per method).

Failure rule: a method fails a case at the first level (mildest first) where its headline metric fails: the metric of
what the model predicts (mean per-image mIoU for classes, matched AP@0.75 for instances) below half its clean mean; for
a model predicting colour only, its mean PSNR more than 6 dB (4x the squared error) below its clean mean. Degradation: the mean over the case's evaluated levels of (level score / clean
score), per method; the method with the highest retained fraction degrades least.
"""

from __future__ import annotations

import csv
import io
import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gpnerf_core.tools.stress.runner import Outcome

FAIL_FRACTION = 0.5
"""mIoU and AP@0.75: failed below this fraction of the clean score."""
SHOWN = (("miou", "mIoU x100", 100.0), ("ap75", "AP@0.75 x100", 100.0), ("psnr", "PSNR dB", 1.0))
"""Metrics in the tables and plots: name, row label, scale."""
SCALE = {name: scale for name, _, scale in SHOWN}
FAIL_PSNR_DROP_DB = 6.0
"""PSNR (models without semantics): failed this many dB below the clean score."""


@dataclass(frozen=True)
class Cell:
    """Mean, std and count over seeds of one metric."""

    mean: float
    std: float
    n: int

    def text(self, scale: float = 1.0, digits: int = 2) -> str:
        if self.n == 1:
            return f"{self.mean * scale:.{digits}f}"
        return f"{self.mean * scale:.{digits}f} ± {self.std * scale:.{digits}f}"


def cell(values: list[float]) -> Cell | None:
    if not values:
        return None
    return Cell(statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0, len(values))


def headline(metrics_names: set[str]) -> str:
    """The metric the failure rule uses, by what the model predicts: mIoU (classes), AP@0.75 (instances), else PSNR."""
    return "miou" if "miou" in metrics_names else "ap75" if "ap75" in metrics_names else "psnr"


def _finite(value: float | None) -> float | str | None:
    return value if value is None or math.isfinite(value) else str(value)


class StressSummary:
    """Aggregates of a suite's outcomes by method, case and level."""

    def __init__(self, outcomes: list[Outcome]) -> None:
        self.outcomes = outcomes
        self.methods = list(dict.fromkeys(o.method for o in outcomes))
        self.cases = list(dict.fromkeys(o.case for o in outcomes if o.case != "clean"))

    def levels(self, case: str) -> list[tuple[float, str]]:
        return list(dict.fromkeys((o.level, o.label) for o in self.outcomes if o.case == case))

    def cell(self, method: str, case: str, level: float | None, metric: str) -> Cell | None:
        values = [o.metrics[metric] for o in self.outcomes
                  if o.method == method and o.case == case and o.level == level and metric in o.metrics]
        return cell(values)

    def skipped(self, method: str, case: str, level: float) -> str | None:
        reasons = [o.skipped for o in self.outcomes
                   if o.method == method and o.case == case and o.level == level and o.skipped]
        return reasons[0] if reasons else None

    def broken(self, method: str, case: str, level: float) -> bool:
        """Some seed of the method gave a non-finite value at this level."""
        return any(o.non_finite for o in self.outcomes if o.method == method and o.case == case and o.level == level)

    def metric_of(self, method: str) -> str:
        names = {k for o in self.outcomes if o.method == method for k in o.metrics}
        return headline(names)

    def failure(self, method: str, case: str) -> str:
        """The first level (mildest first) failing the rule, ``holds`` if none, ``-`` without figures."""
        metric = self.metric_of(method)
        clean = self.cell(method, "clean", None, metric)
        evaluated = False
        for level, label in self.levels(case):
            value = self.cell(method, case, level, metric)
            if clean is None or value is None:
                continue
            evaluated = True
            failed = (value.mean < FAIL_FRACTION * clean.mean if metric != "psnr"
                      else value.mean < clean.mean - FAIL_PSNR_DROP_DB)
            if failed:
                return label
        return "holds" if evaluated else "-"

    def retained(self, method: str, case: str) -> float | None:
        """Mean over the case's evaluated levels of level score / clean score (the headline metric)."""
        metric = self.metric_of(method)
        clean = self.cell(method, "clean", None, metric)
        ratios = [value.mean / clean.mean for level, _ in self.levels(case)
                  if (value := self.cell(method, case, level, metric)) is not None and clean and clean.mean > 0]
        return statistics.fmean(ratios) if ratios else None

    def least_degraded(self, case: str) -> tuple[str, float] | None:
        scored = [(m, r) for m in self.methods if (r := self.retained(m, case)) is not None]
        return max(scored, key=lambda item: item[1]) if scored else None

    def best_at_most_severe(self, case: str) -> tuple[str, str, float] | None:
        """``(method, level label, mean)`` of the highest headline score at the case's most severe evaluated level.

        Degradation is relative to each method's clean score, so a weak method can degrade least and still be the
        worst choice under stress; this names the best absolute score there (methods sharing a headline metric).
        """
        for level, label in reversed(self.levels(case)):
            scored = [(m, c.mean) for m in self.methods
                      if (c := self.cell(m, case, level, self.metric_of(m))) is not None]
            if scored:
                method, value = max(scored, key=lambda item: item[1])
                return method, label, value
        return None

    def non_finite(self) -> list[Outcome]:
        return [o for o in self.outcomes if o.non_finite]

    # ---- outputs -------------------------------------------------------------------------------------------------

    def markdown(self) -> str:
        """Per case: a table of methods x levels (clean first) of mIoU x100 (or AP@0.75 x100) and PSNR, then fails-at
        and retained."""
        lines = []
        for case in self.cases:
            levels = self.levels(case)
            lines += [f"### {case}", ""]
            header = ["method", "metric", "clean", *[label for _, label in levels], "fails at", "retained"]
            lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
            for method in self.methods:
                for metric, shown, scale in SHOWN:
                    digits = 2
                    clean = self.cell(method, "clean", None, metric)
                    if clean is None:
                        continue
                    row = [method, shown, clean.text(scale, digits)]
                    for level, _ in levels:
                        value = self.cell(method, case, level, metric)
                        if self.broken(method, case, level):
                            row.append("NOT FINITE")
                        else:
                            row.append(value.text(scale, digits) if value else
                                       ("skipped" if self.skipped(method, case, level) else "-"))
                    is_headline = metric == self.metric_of(method)
                    retained = self.retained(method, case) if is_headline else None
                    row += [self.failure(method, case) if is_headline else "",
                            f"{retained:.2f}" if retained is not None else ""]
                    lines.append("| " + " | ".join(row) + " |")
            best = self.least_degraded(case)
            reasons = sorted({o.skipped for o in self.outcomes if o.case == case and o.skipped})
            lines.append("")
            if best is not None:
                lines.append(f"Degrades least: {best[0]} (retains {best[1]:.2f} of its clean score on average).")
            top = self.best_at_most_severe(case)
            if top is not None and len(self.methods) > 1:
                scale = SCALE[self.metric_of(top[0])]
                lines.append(f"Highest at the most severe level ({top[1]}): {top[0]} ({top[2] * scale:.2f}).")
            for reason in reasons:
                lines.append(f"Skipped: {reason}.")
            lines.append("")
        return "\n".join(lines)

    def csv(self) -> str:
        out = io.StringIO()
        writer = csv.writer(out)
        writer.writerow(["model", "method", "seed", "case", "level", "label", "miou", "accuracy", "ap75", "psnr",
                         "seconds", "skipped"])
        for o in self.outcomes:
            writer.writerow([o.model, o.method, o.seed, o.case, "" if o.level is None else o.level, o.label,
                             *(o.metrics.get(k, "") for k in ("miou", "accuracy", "ap75", "psnr")), round(o.seconds, 2),
                             o.skipped or ""])
        return out.getvalue()

    def as_json(self) -> dict[str, Any]:
        return {
            "rule": {"fail_fraction_miou": FAIL_FRACTION, "fail_psnr_drop_db": FAIL_PSNR_DROP_DB},
            "outcomes": [
                o.__dict__ | {"metrics": {k: v if math.isfinite(v) else str(v) for k, v in o.metrics.items()},
                              "non_finite": o.non_finite}
                for o in self.outcomes
            ],
            "cases": {
                case: {
                    method: {"fails_at": self.failure(method, case), "retained": _finite(self.retained(method, case))}
                    for method in self.methods
                }
                | {"least_degraded": (self.least_degraded(case) or (None,))[0],
                   "highest_at_most_severe": (self.best_at_most_severe(case) or (None,))[0]}
                for case in self.cases
            },
        }

    def draw(self, folder: Path) -> list[Path]:
        """``<case>.png`` per case: mIoU (or AP@0.75) and PSNR against level, one line per method, seed error bars."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from gpnerf_core.runtime.io import atomic_write_bytes
        from gpnerf_core.registry.components import get_registry

        registered = {name: case for name, (case, _) in get_registry().stress_cases.items()}
        written = []
        for case in self.cases:
            levels = self.levels(case)
            if not any(self.cell(m, case, lv, k) for m in self.methods for lv, _ in levels for k in SCALE):
                continue
            metrics = [k for k in SCALE if any(self.cell(m, "clean", None, k) for m in self.methods)]
            figure, axes = plt.subplots(1, len(metrics), figsize=(5.2 * len(metrics), 3.8), squeeze=False)
            positions = list(range(len(levels) + 1))
            names = ["clean", *[label for _, label in levels]]
            for ax, metric in zip(axes[0], metrics):
                for method in self.methods:
                    cells = [self.cell(method, "clean", None, metric)] + [
                        self.cell(method, case, level, metric) for level, _ in levels
                    ]
                    xs = [p for p, c in zip(positions, cells) if c is not None]
                    if len(xs) < 1:
                        continue
                    scale = SCALE[metric]
                    ax.errorbar(xs, [c.mean * scale for c in cells if c is not None],
                                yerr=[c.std * scale for c in cells if c is not None], marker="o", capsize=3,
                                label=method)
                ax.set_xticks(positions, names, rotation=30 if len(names) > 4 else 0)
                axis = registered[case].axis if case in registered else case
                ax.set_xlabel(axis)
                ax.set_ylabel({"miou": "per-image mIoU x100", "ap75": "matched AP@0.75 x100"}.get(metric, "PSNR (dB)"))
                ax.grid(alpha=0.3)
            axes[0][0].set_title(f"stress: {case}")
            axes[0][-1].legend(fontsize=7)
            figure.tight_layout()
            path = folder / f"{case}.png"
            buffer = io.BytesIO()
            figure.savefig(buffer, format="png", dpi=110)
            plt.close(figure)
            atomic_write_bytes(path, buffer.getvalue())
            written.append(path)
        return written
