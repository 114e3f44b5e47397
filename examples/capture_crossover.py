"""When a capture needs its own model: GP-NeRF zero-shot and fine-tuned against Semantic-NeRF from scratch on one
capture (docs/results_detail.md, "When a scene needs its own model").

    python examples/capture_crossover.py --checkpoint <main job>/checkpoints/step_0000600.pt --work <folder>
        [--seed 0] [--finetune-steps 300] [--scratch-steps 8000] [--grid-steps 2000] [--splat-steps 2000] [--threads 2]
        [--labelled <work of an earlier run>/capture_labelled]

1. The capture of ``capture_adaptation.py`` (the unseen layout filmed as a 40-frame video, ``data prepare-capture``)
   and its labelled copy, which every model here trains and is scored on: the labels are the rendered ones.
2. ``eval`` of the checkpoint on it (zero-shot), ``finetune`` of the checkpoint on its training frames with its own
   loss set (``--finetune-steps``, scored at four points), ``run +experiment=baselines/semantic_nerf`` on the same
   frames from scratch (``--scratch-steps``, scored every 500 steps and at its last), its grid option
   ``baselines/semantic_nerf_grid`` (``--grid-steps``, scored every 250) and per-scene semantic 3D Gaussian splatting
   ``baselines/semantic_3dgs`` (``--splat-steps``, scored every 250; it starts from the capture's sparse points), all
   at the main job's 96 x 128, each scored on the capture's held-out frames. 0 steps leaves a row out (the fine-tuning
   or a from-scratch one); ``--labelled`` reuses an earlier run's labelled capture (the same frames and poses for
   every seed) instead of making it again.
Prints one JSON object (steps, training seconds, per-image mIoU, PSNR and seconds per rendered frame of each row) and
writes it to ``<work>/crossover.json``. Each step is a real command line; its log is in ``<work>``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from capture_adaptation import SIZE, command, make_capture

SCORES = ("miou/image_mean_present", "psnr/clamped")


def row(values: dict, step: int, seconds: float) -> dict:
    return {"step": step, "train_seconds": round(seconds, 1), **{key: values.get(key) for key in SCORES}}


def scratch_rows(metrics: dict) -> list[dict]:
    """The from-scratch run's scores at every evaluated step, its final evaluation last."""
    rows = [row(point["train_heldout"], point["step"], point["train_seconds"]) for point in metrics.get("eval_curve", [])]
    train = metrics["train"]
    if not rows or rows[-1]["step"] != train["steps"]:
        rows.append(row(metrics["eval"]["train_heldout"], train["steps"], train["seconds"]))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--finetune-steps", type=int, default=300)
    parser.add_argument("--scratch-steps", type=int, default=8000)
    parser.add_argument("--grid-steps", type=int, default=2000)
    parser.add_argument("--splat-steps", type=int, default=2000)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--labelled", type=Path, help="an earlier run's capture_labelled folder, reused as it is")
    args = parser.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    checkpoint = str(args.checkpoint.resolve())
    seconds: dict[str, float] = {}
    if args.labelled is not None:
        labelled = args.labelled.resolve()
        if not (labelled / "transforms.json").is_file():
            sys.exit(f"--labelled {labelled}: expected a labelled capture (its transforms.json), found none")
    else:
        _, labelled = make_capture(work, seconds)
    common = ["dataset=capture", f"dataset.root={labelled}", *SIZE, f"threads={args.threads}", "overwrite=true"]
    scene = "dataset.scenes=[capture_labelled]"

    seconds["zero_shot"] = command(work, "zero_shot", "eval", f"checkpoint={checkpoint}", *common,
                                   f"out_dir={work / 'zero_shot'}")
    if args.finetune_steps > 0:
        seconds["finetune"] = command(work, "finetune", "finetune", f"checkpoint={checkpoint}", *common, scene,
                                      f"train.steps={args.finetune_steps}", "finetune.points=4", f"seed={args.seed}",
                                      f"out_dir={work / 'finetune'}")
    scratch_runs = {"semantic_nerf": (args.scratch_steps, 500), "semantic_nerf_grid": (args.grid_steps, 250),
                    "semantic_3dgs": (args.splat_steps, 250)}
    for name, (steps, every) in scratch_runs.items():
        if steps > 0:
            seconds[name] = command(work, name, "run", f"+experiment=baselines/{name}", *common, scene,
                                    f"train.steps={steps}", f"eval.every_steps={every}", "eval.save_images=0",
                                    f"seed={args.seed}", f"out_dir={work / name}")

    def metrics(name: str) -> dict:
        return json.loads((work / name / "metrics.json").read_text())

    zero_shot = metrics("zero_shot")["eval"]["train_heldout"]
    finetuned = metrics("finetune")["finetune"]["curve"] if "finetune" in seconds else []
    result = {
        "held_out_images": zero_shot.get("count/images"),
        "gpnerf_zero_shot": row(zero_shot, 0, 0.0),
        "gpnerf_finetuned": [row(point, point["step"], point["train_seconds"]) for point in finetuned],
        **{name: scratch_rows(metrics(name)) for name in seconds if name in scratch_runs},
        "command_seconds": {key: round(value, 1) for key, value in seconds.items()},
    }
    (work / "crossover.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
