"""Generalized start, per-scene finish: accuracy against per-scene training seconds on one scene, one curve per model
(docs/results.md, "From the first second to the scene's own model"; docs/fit.md).

    python examples/start_crossover.py --work <folder> --gpnerf <main job .pt> --mvsplat <mvsplat_unet .pt> \
        [--capture <labelled capture folder>] [--seed 0] [--threads 1] [--rows zero_shot,finetune,grid,...]

Rows (each one real command line, its log and run folder in ``<work>/<row>``; a row whose ``metrics.json`` exists is
kept, so an interrupted batch goes on where it stopped):

- ``zero_shot`` / ``zero_shot_mvsplat``: ``eval`` of the generalizable checkpoints on the scene (their value at 0 s);
- ``finetune``: GP-NeRF fine-tuned on the scene's training frames (``finetune``, 300 steps, 7 points);
- ``grid``: Semantic-NeRF's grid option from scratch (``run +experiment=baselines/semantic_nerf_grid``, 2000 steps,
  scored every 250);
- ``splat_points``: Semantic 3DGS from the scene's sparse points or depth (``fit``, 2000 steps, scored every 50);
- ``splat_gpnerf`` / ``splat_mvsplat``: Semantic 3DGS started from GP-NeRF's / MVSplat's prediction (``fit
  checkpoint=...``, the same steps and scoring);
- ``splat_points_gpnerf``: Semantic 3DGS from the scene's points with GP-NeRF's semantics (``fit checkpoint=...
  fit.start_geometry=points``: the geometry of ``splat_points``, the features and head of ``splat_gpnerf``).

The scene is the embedded unseen layout (``unseen_00``) or, with ``--capture``, a labelled capture at the main job's
96 x 128 (``examples/capture_adaptation.py`` makes the unseen layout filmed and another layout from photos). Every row
is scored on the scene's held-out frames, which nothing trains on. Writes ``<work>/curves.json``: per row, its points
``{step, seconds, miou, miou_dataset, psnr}`` (seconds: per-scene training seconds, the start's own seconds included
for a started model; 0 for zero-shot).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from capture_adaptation import command

ROWS = ("zero_shot", "zero_shot_mvsplat", "finetune", "grid", "splat_points", "splat_gpnerf", "splat_mvsplat",
        "splat_points_gpnerf")
SCORES = {"miou": "miou/image_mean_present", "miou_dataset": "miou/dataset", "psnr": "psnr/clamped"}


def row_commands(args: argparse.Namespace, work: Path) -> dict[str, list[str]]:
    """Each row's command line (``out_dir`` and ``overwrite`` added by the caller)."""
    if args.capture is not None:
        capture = args.capture.resolve()
        data = ["dataset=capture", f"dataset.root={capture}", f"dataset.scenes=[{capture.name}]", "dataset.height=96",
                "dataset.width=128"]
    else:
        data = ["dataset.scenes=[unseen_00]"]
    common = [*data, f"threads={args.threads}", f"seed={args.seed}", "eval.save_images=0"]
    fit = ["fit", *common, f"train.steps={args.splat_steps}", f"fit.eval_every={args.splat_every}"]
    return {
        "zero_shot": ["eval", f"checkpoint={args.gpnerf.resolve()}", *data, f"threads={args.threads}",
                      "eval.save_images=0"],
        "zero_shot_mvsplat": ["eval", f"checkpoint={args.mvsplat.resolve()}", *data, f"threads={args.threads}",
                              "eval.save_images=0"],
        "finetune": ["finetune", f"checkpoint={args.gpnerf.resolve()}", *common, f"train.steps={args.finetune_steps}",
                     "finetune.points=7"],
        "grid": ["run", "+experiment=baselines/semantic_nerf_grid", *common, f"train.steps={args.grid_steps}",
                 "eval.every_steps=250"],
        "splat_points": fit,
        "splat_gpnerf": [*fit, f"checkpoint={args.gpnerf.resolve()}"],
        "splat_mvsplat": [*fit, f"checkpoint={args.mvsplat.resolve()}"],
        "splat_points_gpnerf": [*fit, f"checkpoint={args.gpnerf.resolve()}", "fit.start_geometry=points"],
    }


def point(values: dict, step: int, seconds: float) -> dict:
    return {"step": step, "seconds": round(float(seconds), 2), **{k: values.get(v) for k, v in SCORES.items()}}


def curve(row: str, metrics: dict) -> list[dict]:
    """A row's points from its ``metrics.json``, in order of seconds."""
    if row.startswith("zero_shot"):
        return [point(metrics["eval"]["train_heldout"], 0, 0.0)]
    if row == "finetune":
        return [point(p, p["step"], p["train_seconds"]) for p in metrics["finetune"]["curve"]]
    if row.startswith("splat"):
        return [point(p, p["step"], p["seconds"]) for p in metrics["fit"]["curve"]]
    points = [point(p["train_heldout"], p["step"], p["train_seconds"]) for p in metrics.get("eval_curve", [])]
    if not points or points[-1]["step"] != metrics["train"]["steps"]:
        points.append(point(metrics["eval"]["train_heldout"], metrics["train"]["steps"], metrics["train"]["seconds"]))
    return points


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--gpnerf", type=Path, required=True, help="the main job's checkpoint (GP-NeRF)")
    parser.add_argument("--mvsplat", type=Path, required=True, help="a baselines/mvsplat_unet checkpoint")
    parser.add_argument("--capture", type=Path, help="a labelled capture folder (default: the embedded unseen_00)")
    parser.add_argument("--name", help="the scene's name on the chart (default: the capture folder's, or unseen_00)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rows", default=",".join(ROWS))
    parser.add_argument("--finetune-steps", type=int, default=300)
    parser.add_argument("--grid-steps", type=int, default=2000)
    parser.add_argument("--splat-steps", type=int, default=2000)
    parser.add_argument("--splat-every", type=int, default=50)
    args = parser.parse_args()
    rows = [row for row in args.rows.split(",") if row]
    unknown = sorted(set(rows) - set(ROWS))
    if unknown:
        sys.exit(f"--rows: unknown {', '.join(unknown)}; expected some of {', '.join(ROWS)}")
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    commands = row_commands(args, work)
    for row in rows:
        if not (work / row / "metrics.json").is_file():
            command(work, row, *commands[row], f"out_dir={work / row}", "overwrite=true")
    scene = args.name or (args.capture.resolve().name if args.capture else "unseen_00")
    result = {"seed": args.seed, "scene": scene,
              **{row: curve(row, json.loads((work / row / "metrics.json").read_text()))
                 for row in ROWS if (work / row / "metrics.json").is_file()}}
    (work / "curves.json").write_text(json.dumps(result, indent=1))
    print(json.dumps({row: value[-1] if isinstance(value, list) else value for row, value in result.items()},
                     indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
