"""Resume bit for bit, every family: each experiment trains ``steps`` steps straight (a checkpoint halfway), then again
from that halfway checkpoint (what a kill after it leaves, ``train.resume=<file>``); the final checkpoints' model
tensors and the final loss must be identical. One row per experiment, exit 1 if any differs.

    python examples/resume_check.py [steps=10] [threads=2] [names=main,mvsplat,...] [out=/tmp/resume_check]

Each run is a subprocess of ``python -m gpnerf_core run`` with ``eval.max_views_per_scene=1``; a per-scene family
trains on ``layout_00``. ``+experiment=gaussian_grouping`` joins when the example package is installed.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import torch

PER_SCENE = ["dataset.scenes=[layout_00]"]
EXPERIMENTS = {
    "main": ["+head=unet", "+loss=dgs"],
    "neuray": ["+experiment=baselines/neuray"],
    "semantic_ray": ["+experiment=baselines/semantic_ray"],
    "mvsnerf": ["+experiment=baselines/mvsnerf"],
    "mvsplat": ["+experiment=baselines/mvsplat"],
    "semantic_nerf": ["+experiment=baselines/semantic_nerf", *PER_SCENE],
    "semantic_nerf_grid": ["+experiment=baselines/semantic_nerf_grid", *PER_SCENE],
    "dm_nerf": ["+experiment=baselines/dm_nerf", *PER_SCENE],
    "semantic_3dgs": ["+experiment=baselines/semantic_3dgs", *PER_SCENE],
    "gaussian_grouping": ["+experiment=gaussian_grouping", *PER_SCENE],
}


def options(argv: list[str]) -> dict[str, str]:
    parsed = dict(item.split("=", 1) for item in argv)
    unknown = set(parsed) - {"steps", "threads", "names", "out"}
    if unknown:
        raise SystemExit(f"unknown option {sorted(unknown)[0]!r}; expected steps=, threads=, names=, out=")
    return parsed


def installed(name: str) -> bool:
    from gpnerf_core import get_registry

    return name != "gaussian_grouping" or "gaussian_grouping" in get_registry().components["model"]


def train(overrides: list[str], out: Path, extra: list[str]) -> dict:
    result = subprocess.run([sys.executable, "-m", "gpnerf_core", "run", *overrides, *extra, f"out_dir={out}"],
                            capture_output=True, text=True)
    if result.returncode:
        raise SystemExit(f"run {' '.join(overrides)} failed: {result.stderr.strip().splitlines()[-1]}")
    return json.loads((out / "metrics.json").read_text())


def model_tensors(checkpoint: Path) -> dict[str, torch.Tensor]:
    return torch.load(checkpoint, weights_only=False)["model"]


def main(argv: list[str]) -> int:
    o = options(argv)
    steps, threads = int(o.get("steps", 10)), int(o.get("threads", 2))
    names = o["names"].split(",") if "names" in o else list(EXPERIMENTS)
    root = Path(o.get("out", "/tmp/resume_check"))
    half = steps // 2
    common = [f"train.steps={steps}", f"train.checkpoint_every={half}", f"threads={threads}", "seed=0",
              "eval.max_views_per_scene=1", "eval.save_images=0", "overwrite=true"]
    print("| experiment | steps | resumed from | final loss straight / resumed | model tensors | identical |")
    print("|---|---|---|---|---|---|")
    failed = 0
    for name in names:
        if not installed(name):
            print(f"| {name} | | | not installed | | skipped |")
            continue
        began = time.perf_counter()
        straight = train(EXPERIMENTS[name], root / name / "straight", common)
        middle = root / name / "straight" / "checkpoints" / f"step_{half:07d}.pt"
        resumed = train(EXPERIMENTS[name], root / name / "resumed", [*common, f"train.resume={middle}"])
        final = f"checkpoints/step_{steps:07d}.pt"
        a, b = model_tensors(root / name / "straight" / final), model_tensors(root / name / "resumed" / final)
        same = a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
        losses = straight["train"]["final_loss"], resumed["train"]["final_loss"]
        same = same and losses[0] == losses[1]
        failed += not same
        print(f"| {name} | {steps} | {half} | {losses[0]:.6g} / {losses[1]:.6g} | {len(a)} | "
              f"{'yes' if same else 'NO'} ({time.perf_counter() - began:.0f} s) |", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
