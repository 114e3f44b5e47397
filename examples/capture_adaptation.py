"""A generalized model adapted to a capture without labels, measured end to end (docs/datasets/capture.md).

    python examples/capture_adaptation.py --checkpoint <main job>/checkpoints/step_0000600.pt --work <folder>

1. Renders a room the checkpoint never saw (the embedded generator's unseen layout, 40 frames of 320x240 on an orbit)
   and writes it as an MP4: the "phone video".
2. ``data prepare-capture`` turns the video into a capture (frames, structure from motion, transforms.json).
3. A copy of the capture gets the rendered labels of its frames (``semantic_file_path`` + classes.json) for scoring
   only: no command below trains on them (``label_free`` reads no label; the refusal of label losses on unlabelled
   scenes is tested elsewhere).
4. ``eval`` of the checkpoint on the unlabelled capture (RGB and depth metrics, label metrics not available) and
   ``finetune +loss=label_free`` for ``--steps`` steps, evaluated at 0, N/4, N/2, 3N/4 and N (held-out PSNR; mIoU on
   the labelled copy), against a colour-only model (``+loss=rgb``, no head) trained from scratch on the same frames for
   the same steps (``eval.every_steps``).
Prints a table and writes ``<work>/adaptation.json``. Each step is a real command line; its log is in ``<work>``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import imageio.v2 as imageio

SIZE = ["dataset.height=96", "dataset.width=128"]
"""The capture is loaded at the main job's training size."""


def command(work: Path, name: str, *args: str) -> float:
    """``python -m gpnerf_core <args>`` with its log in ``<work>/<name>.log``; its wall seconds."""
    started = time.perf_counter()
    with open(work / f"{name}.log", "w") as log:
        done = subprocess.run([sys.executable, "-m", "gpnerf_core", *args], stdout=log, stderr=subprocess.STDOUT)
    if done.returncode != 0:
        sys.exit(f"{name} failed (exit {done.returncode}); see {work / f'{name}.log'}")
    return time.perf_counter() - started


def labelled_copy(capture: Path, sequence: Path, out: Path) -> None:
    """``capture`` with each frame's rendered labels attached (for scoring only)."""
    shutil.copytree(capture, out)
    transforms = json.loads((out / "transforms.json").read_text())
    (out / "semantics").mkdir()
    sources = transforms["gpnerf_summary"]["source_frames"]
    for frame in transforms["frames"]:
        name = Path(frame["file_path"]).name
        index = int(Path(str(sources[name])).stem.split("_")[-1])  # the video frame, or the photo IMG_<frame>.jpg
        shutil.copyfile(sequence / "semantic_class" / f"semantic_class_{index}.png", out / "semantics" / name)
        frame["semantic_file_path"] = f"semantics/{name}"
    (out / "transforms.json").write_text(json.dumps(transforms, indent=1))
    classes = json.loads((sequence.parents[1] / "classes.json").read_text())
    (out / "classes.json").write_text(json.dumps({"classes": classes["class_names"], "ignore_index": classes["ignore_index"]}))


def make_capture(work: Path, seconds: dict[str, float], *, photos_of_seed: int | None = None) -> tuple[Path, Path]:
    """Steps 1-3 in ``work``: the "phone video" of the unseen layout, its capture (``data prepare-capture``) and the
    capture's labelled copy; returns both folders, the commands' seconds in ``seconds``. ``photos_of_seed``: instead,
    another layout (the unseen layout the generator makes with that seed) as a folder of 40 JPEG photos
    (``IMG_<frame>.jpg``), prepared with the exhaustive matcher as photos not taken in order are."""
    scenes = work / "embedded"
    seed = [] if photos_of_seed is None else ["--seed", str(photos_of_seed)]
    seconds["render"] = command(work, "make", "data", "make", "--root", str(scenes), "--num-train-scenes", "1",
                                "--num-unseen-scenes", "1", "--frames-per-scene", "40", "--height", "240",
                                "--width", "320", *seed)
    sequence = next(scenes.glob("unseen_00/*"))
    frames = [imageio.imread(sequence / "rgb" / f"rgb_{i}.png") for i in range(40)]
    if photos_of_seed is None:
        source = work / "unseen_00.mp4"
        imageio.mimsave(source, frames, fps=10, codec="libx264", macro_block_size=1)
        how = ["--frames", "40"]
    else:
        source = work / "photos"
        source.mkdir(exist_ok=True)
        for i, frame in enumerate(frames):
            imageio.imwrite(source / f"IMG_{i:04d}.jpg", frame[..., :3], quality=92)
        how = ["--matcher", "exhaustive"]

    capture = work / "capture"
    if capture.exists():
        shutil.rmtree(capture)
    seconds["prepare_capture"] = command(work, "prepare", "data", "prepare-capture", str(source), "--out", str(capture),
                                         *how)
    labelled = work / "capture_labelled"
    if labelled.exists():
        shutil.rmtree(labelled)
    labelled_copy(capture, sequence, labelled)
    return capture, labelled


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=200)
    args = parser.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    checkpoint = str(args.checkpoint.resolve())
    seconds: dict[str, float] = {}

    capture, labelled = make_capture(work, seconds)

    seconds["eval_unlabelled"] = command(work, "eval", "eval", f"checkpoint={checkpoint}", "dataset=capture",
                                         f"dataset.root={capture}", *SIZE, f"out_dir={work / 'eval'}", "overwrite=true")
    points = 5
    seconds["finetune_label_free"] = command(
        work, "finetune", "finetune", f"checkpoint={checkpoint}", "dataset=capture", f"dataset.root={labelled}",
        "dataset.scenes=[capture_labelled]", "+loss=label_free", f"train.steps={args.steps}",
        f"finetune.points={points}", *SIZE, f"out_dir={work / 'finetune'}", "overwrite=true")
    seconds["rgb_from_scratch"] = command(
        work, "scratch", "run", "+loss=rgb", "dataset=capture", f"dataset.root={capture}", f"train.steps={args.steps}",
        f"eval.every_steps={args.steps // (points - 1)}", "eval.splits=[train]", *SIZE, f"out_dir={work / 'scratch'}",
        "overwrite=true")

    prepared = json.loads((capture / "transforms.json").read_text())["gpnerf_summary"]
    evaluated = json.loads((work / "eval" / "metrics.json").read_text())["eval"]["train_heldout"]
    finetune = json.loads((work / "finetune" / "metrics.json").read_text())["finetune"]["curve"]
    scratch = json.loads((work / "scratch" / "metrics.json").read_text())["eval_curve"]
    result = {
        "capture": {"registered": prepared["registered_frames"], "given": prepared["given_frames"],
                    "seconds": prepared["seconds"]},
        "eval_unlabelled": {k: evaluated.get(k) for k in ("psnr/clamped", "ssim/gaussian11", "miou/image_mean_present",
                                                           "labels/unavailable_reason")},
        "label_free": [{k: e.get(k) for k in ("step", "psnr/clamped", "miou/image_mean_present")} for e in finetune],
        "rgb_from_scratch": [{"step": e["step"], "psnr/clamped": e["train_heldout"].get("psnr/clamped")}
                             for e in scratch],
        "command_seconds": {k: round(v, 1) for k, v in seconds.items()},
    }
    (work / "adaptation.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
