"""``python -m gpnerf_core report <folders> [--chart DIR]``: one table from many run folders (a sweep, an ablation,
seeds) beside the paper's Table 4, and optionally the accuracy-against-cost chart (``gpnerf_core.tools.reporting``)."""

from __future__ import annotations

import sys
from pathlib import Path

from gpnerf_core.config.arguments import ArgumentParser
from gpnerf_core.errors import DataError
from gpnerf_core.runtime.io import check_output_folder
from gpnerf_core.tools.reporting.runs import (
    find_runs,
    format_table,
    fronts_possible,
    group_runs,
    method_labels,
    with_parameter_count,
)
from gpnerf_core.tools.reporting.speed_accuracy import draw, methods_from_groups


def main(argv: list[str]) -> int:
    parser = ArgumentParser(prog="gpnerf_core report", description="Tabulate run folders (mIoU is the per-image protocol, x100).")
    parser.add_argument("paths", nargs="+", type=Path)
    parser.add_argument("--chart", type=Path, metavar="DIR",
                        help="also draw accuracy against cost (speed_accuracy.png, .csv, pareto.txt in DIR)")
    args = parser.parse_args(argv)
    if args.chart is not None:
        check_output_folder(args.chart, "--chart")
    rows = find_runs(args.paths)
    if not rows:
        raise DataError(f"no run folders (metrics.json + config.yaml) under {', '.join(map(str, args.paths))}")
    print(format_table(rows))
    without_metrics = [row for row in rows if row.state != "finished"]
    if without_metrics:
        print(f"note: {len(without_metrics)} of {len(rows)} run folder(s) have no metrics.json (failed or unfinished: "
              "their rows say why); the table's numbers are the other runs'", file=sys.stderr)
    if args.chart is not None:
        groups = group_runs([with_parameter_count(row) for row in rows])
        methods = methods_from_groups(groups, method_labels(groups))
        if not any(fronts_possible(m) for m in methods):
            raise DataError("--chart: no run has both an accuracy (mIoU, PSNR, AP) and a cost (time, rays/s, "
                            "s/frame, parameters, memory) in its metrics.json; nothing to draw")
        fronts = draw(methods, args.chart)
        print(f"\nPareto fronts (speed_accuracy.png, speed_accuracy.csv, pareto.txt in {args.chart}):")
        for panel, names in fronts.items():
            print(f"  {panel}: {', '.join(names)}")
    return 0
