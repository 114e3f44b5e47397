"""``python -m gpnerf_core report <folders>``: one table from many run folders (a sweep, an ablation).

Rows are the run folders found below the given paths (any folder holding ``metrics.json`` and ``config.yaml``).
Runs whose settings match a row of the paper's Table 4 get that row's ID and the paper's numbers beside them;
the paper's numbers are ScanNet at full size, so they are context, not a target for CPU-sized runs.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from gpnerf_core.errors import ConfigError, DataError

# Table 4 of the paper: (joint attention, S.D, gradient block, D.G) -> (ID, mIoU, PSNR) on ScanNet.
PAPER_TABLE4 = {
    (False, False, False, False): ("1", 56.45, 29.06),
    (True, False, False, False): ("2", 57.19, 29.30),
    (True, True, False, False): ("3", 52.03, 29.29),
    (True, True, True, False): ("4", 59.55, 29.26),
    (True, True, True, True): ("5", 59.92, 29.37),
}


@dataclass(frozen=True)
class RunRow:
    folder: Path
    config: dict[str, Any]
    metrics: dict[str, Any]

    def switches(self) -> tuple[bool, bool, bool, bool] | None:
        loss = self.config.get("loss") or {}
        if not loss:
            return None
        joint = bool(self.config["model"]["semantic_field"]["joint_attention"])
        sd = float(loss.get("sd_weight", 0)) > 0
        dgs = float(loss.get("dgs_weight", 0)) > 0
        block = bool(loss.get("teacher_stop_grad", False)) and (sd or dgs)
        return joint, sd, block, dgs


def find_runs(paths: list[Path]) -> list[RunRow]:
    rows = []
    for path in paths:
        if not path.exists():
            raise DataError(f"{path}: expected a run folder or a folder of runs, found nothing")
        for metrics_file in sorted(path.rglob("metrics.json")):
            folder = metrics_file.parent
            config_file = folder / "config.yaml"
            if not config_file.is_file():
                continue
            try:
                metrics = json.loads(metrics_file.read_text())
                config = yaml.safe_load(config_file.read_text())
            except (json.JSONDecodeError, yaml.YAMLError) as exc:
                raise DataError(f"{metrics_file}: could not be parsed ({type(exc).__name__})") from None
            rows.append(RunRow(folder, config, metrics))
    return rows


def _value(metrics: dict[str, Any], split: str, key: str, scale: float = 1.0, digits: int = 2) -> str:
    value = metrics.get("eval", {}).get(split, {}).get(key)
    return "n/a" if value is None else f"{value * scale:.{digits}f}"


def format_table(rows: list[RunRow]) -> str:
    header = (
        "| run | head | loss | joint attn | S.D | grad block | D.G | steps | mIoU held-out | mIoU unseen "
        "| PSNR held-out | train s | Table 4 ID | paper mIoU | paper PSNR |"
    )
    lines = [header, "|" + "|".join(["---"] * 15) + "|"]
    for row in rows:
        switches = row.switches()
        paper = PAPER_TABLE4.get(switches) if switches else None
        flags = ["yes" if s else "no" for s in switches] if switches else ["-"] * 4
        head = (row.config.get("head") or {}).get("name", "-")
        loss = (row.config.get("loss") or {}).get("name", "-")
        train = row.metrics.get("train", {})
        lines.append(
            "| "
            + " | ".join(
                [
                    row.folder.name,
                    head,
                    loss,
                    *flags,
                    str(train.get("steps", "-")),
                    _value(row.metrics, "train_heldout", "miou/image_mean_present", 100),
                    _value(row.metrics, "unseen", "miou/image_mean_present", 100),
                    _value(row.metrics, "train_heldout", "psnr/clamped"),
                    str(train.get("seconds", "-")),
                    paper[0] if paper else "-",
                    f"{paper[1]:.2f}" if paper else "-",
                    f"{paper[2]:.2f}" if paper else "-",
                ]
            )
            + " |"
        )
    return "\n".join(lines)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:
        raise ConfigError(f"{self.prog}: {message}")


def main(argv: list[str]) -> int:
    parser = _Parser(prog="gpnerf_core report", description="Tabulate run folders (mIoU is the per-image protocol, x100).")
    parser.add_argument("paths", nargs="+", type=Path)
    args = parser.parse_args(argv)
    rows = find_runs(args.paths)
    if not rows:
        raise DataError(f"no run folders (metrics.json + config.yaml) under {', '.join(map(str, args.paths))}")
    print(format_table(rows))
    return 0
