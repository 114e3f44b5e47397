"""The GPU check's steps, run by ``gpu_check/run.sh`` (``python gpu_check/checks.py <out folder>``).

Each step is a subprocess with its own time limit; a failed step is recorded and the next one runs. The output folder
gets ``gpu_check.log`` (every step's output), one file per step's results and ``summary.txt`` (what
docs/benchmarks.md quotes). ``GPU_CHECK_DRY_RUN=1`` runs the same steps on the CPU at tiny sizes (the wiring only).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DRY = bool(os.environ.get("GPU_CHECK_DRY_RUN"))
DEVICE = "cpu" if DRY else "cuda"
TINY = ["dataset.num_train_scenes=1", "dataset.num_unseen_scenes=1", "dataset.frames_per_scene=6", "dataset.eval_every=3",
        "dataset.height=32", "dataset.width=48", "model.feature_extractor.widths=[8,8,8,16]", "model.feature_extractor.fpn_channels=4",
        "model.field_aggregator.width=16", "model.field_aggregator.num_blocks=2", "model.coarse_samples=6", "model.fine_samples=2",
        "model.num_source_views=2", "train.rays=16", "train.steps=2", "eval.save_images=0"]
PAPER_BENCH_DATA = ["scale=paper", "dataset.height=240", "dataset.width=320", "dataset.num_train_scenes=1",
                    "dataset.num_unseen_scenes=1", "dataset.frames_per_scene=16"]
SCENE_SETS = {
    "suite": ["+head=unet", "+loss=dgs", *TINY],  # tests/pipeline_check.py's TINY_SCENES
    "main_job": ["+head=unet", "+loss=dgs"],
    "bench_paper": ["+head=unet", "+loss=dgs", *PAPER_BENCH_DATA],
}
"""Configs whose embedded scene sets ``prepare.sh`` renders into ``gpu_check/cache`` (the image has no pybullet)."""

BENCH = ["size=demo", "repeats=1", "warmup=1", "train.steps=2"] if DRY else ["size=paper", "repeats=3", "warmup=1"]
STEPS = [
    ("cuda_tests", 180, [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
                         "tests/training/test_device_placement.py", "-k", "cuda" if not DRY else "default_device"]),
    ("main_job", 240, [sys.executable, "-m", "gpnerf_core", "run", "+head=unet", "+loss=dgs", f"device={DEVICE}",
                       "out_dir={out}/main_job", *(["train.steps=2", "eval.max_views_per_scene=1"] if DRY else [])]),
    ("rasterizer_backends", 90, [sys.executable, "gpu_check/rasterizer.py", "{out}/rasterizer.json"]),
    ("mvsplat_unet", 150, [sys.executable, "-m", "gpnerf_core", "run", "+experiment=baselines/mvsplat_unet",
                           f"device={DEVICE}", "out_dir={out}/mvsplat_unet",
                           *(["train.steps=2", "eval.max_views_per_scene=1"] if DRY else ["train.steps=100"])]),
    ("bench_fp32", 150, [sys.executable, "-m", "gpnerf_core", "bench", *BENCH, f"device={DEVICE}",
                         "out_dir={out}/bench_fp32"]),
    ("bench_bf16", 150, [sys.executable, "-m", "gpnerf_core", "bench", *BENCH, f"device={DEVICE}",
                         "train.precision=bf16", "out_dir={out}/bench_bf16"]),
    ("bench_compiled", 180, [sys.executable, "-m", "gpnerf_core", "bench", *BENCH, f"device={DEVICE}",
                             "model.compile=true", *(["model.compile_backend=aot_eager"] if DRY else []),
                             "out_dir={out}/bench_compiled"]),
    ("torchrun_nccl", 90, [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=1",
                           "-m", "gpnerf_core", "run", "+head=unet", "+loss=dgs", *TINY, f"device={DEVICE}",
                           "out_dir={out}/torchrun"]),
]
"""(name, seconds allowed, command): about 20 minutes at most, about 8 expected on an H200 (compilation with
Triton included in the compiled bench's warm-up); the steps run in this order, so the ones every GPU session should see
come first."""


def machine() -> dict[str, object]:
    import torch

    info: dict[str, object] = {"torch": torch.__version__, "cuda": torch.version.cuda,
                               "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"}
    try:
        info["nvidia_smi"] = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total,driver_version",
                                             "--format=csv,noheader"], capture_output=True, text=True,
                                            timeout=30).stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        info["nvidia_smi"] = None
    return info


def summarize(out: Path, name: str) -> str:
    """The figures a step produced, on one line."""
    if name == "main_job" and (out / "main_job" / "metrics.json").is_file():
        metrics = json.loads((out / "main_job" / "metrics.json").read_text())
        held, unseen = metrics["eval"].get("train_heldout", {}), metrics["eval"].get("unseen", {})
        return (f"held-out mIoU {held.get('miou/image_mean_present')}, unseen mIoU "
                f"{unseen.get('miou/image_mean_present')}, train {metrics['train']['seconds']} s "
                f"({metrics['train']['rays_per_second']} rays/s), backend {metrics['train']['backend']}")
    if name.startswith("bench") and (out / name / "bench.json").is_file():
        report = json.loads((out / name / "bench.json").read_text())
        parts = []
        for size, entry in report["sizes"].items():
            for variant in ("gpnerf", "gnt_only"):
                train, render = entry[variant].get("train", {}), entry[variant].get("render", {})
                rays_per_second = (round(render["rays"] / render["seconds_min"]) if render.get("rays")
                                   and render.get("seconds_min") else None)
                parts.append(f"{size} {variant}: step {train.get('seconds_min')} s, train peak "
                             f"{train.get('peak_memory_mb')} MiB, render {rays_per_second} rays/s, render peak "
                             f"{render.get('peak_memory_mb')} MiB" + (f", error {train.get('error') or render.get('error')}"
                                                                     if "error" in train or "error" in render else ""))
        return "; ".join(parts)
    if name == "rasterizer_backends" and (out / "rasterizer.json").is_file():
        report = json.loads((out / "rasterizer.json").read_text())
        parts = [report["gsplat"]] if "gsplat" in report else []
        for case in report["cases"]:
            timed = {k: v for k, v in case.items() if isinstance(v, dict) and "render_ms" in v}
            parts.append(f"{case['gaussians']} Gaussians at {case['size']}: " + ", ".join(
                f"{backend} {v['render_ms']} / {v['forward_backward_ms']} ms" for backend, v in timed.items())
                + (f", max difference {max(case['max_abs_difference'].values()):.2e}"
                   if "max_abs_difference" in case else ""))
        return "; ".join(parts)
    if name == "mvsplat_unet" and (out / "mvsplat_unet" / "metrics.json").is_file():
        metrics = json.loads((out / "mvsplat_unet" / "metrics.json").read_text())
        held = metrics["eval"].get("train_heldout", {})
        return (f"held-out mIoU {held.get('miou/image_mean_present')}, PSNR {held.get('psnr/clamped')}, "
                f"train {metrics['train']['seconds']} s")
    if name == "torchrun_nccl" and (out / "torchrun" / "metrics.json").is_file():
        train = json.loads((out / "torchrun" / "metrics.json").read_text())["train"]
        return f"world size {train['world_size']}, backend {train['backend']}, {train['steps']} steps"
    return ""


def main(out: Path) -> int:
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, GPNERF_DISABLE_PLUGIN_AUTOLOAD="1", PYTHONUNBUFFERED="1")
    if not DRY:  # the prepared sets; a dry run renders (or reuses) its own in the usual cache
        env["GPNERF_CACHE"] = str(REPO / "gpu_check" / "cache")
    lines = [f"gpu check {time.strftime('%Y-%m-%d %H:%M:%S')} (dry run on the CPU)" if DRY else
             f"gpu check {time.strftime('%Y-%m-%d %H:%M:%S')}", json.dumps(machine())]
    failed = 0
    with open(out / "gpu_check.log", "w") as log:
        for name, limit, command in STEPS:
            command = [part.replace("{out}", str(out)) for part in command]
            log.write(f"\n===== {name}: {' '.join(command)}\n")
            log.flush()
            started = time.perf_counter()
            try:
                code = subprocess.run(command, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT,
                                      timeout=limit).returncode
            except subprocess.TimeoutExpired:
                code = "timeout"
            seconds = time.perf_counter() - started
            failed += code != 0
            line = f"{name}: {'ok' if code == 0 else f'FAILED ({code})'} in {seconds:.0f} s. {summarize(out, name)}"
            lines.append(line)
            print(line, flush=True)
    (out / "summary.txt").write_text("\n".join(lines) + "\n")
    print(f"summary in {out / 'summary.txt'}; every step's output in {out / 'gpu_check.log'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/gpu_check")))
