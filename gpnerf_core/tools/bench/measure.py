"""One benchmark measurement, in its own process so its peak memory is its own.

    python -m gpnerf_core.tools.bench.measure '<spec as JSON>'

The spec names the overrides (``run``'s), the phase (``train``: sample, forward, loss, backward, Adam step;
``render``: ``GeneralizableNeRF.predict`` on a whole held-out view), warm-up and repetitions, and a progress file.
The last line on stdout is the result as JSON; the progress file holds the peak memory after every repetition, so a
measurement killed for memory still says how far it got.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import torch

from gpnerf_core.interfaces.model import parameter_counts
from torch.utils.flop_counter import FlopCounterMode

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.runtime.device import peak_memory_mb
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.data.frames import FrameCache, choose_sources
from gpnerf_core.model.checkpoint import RunRecord
from gpnerf_core.training.trainer import Trainer
from gpnerf_core.engine.setup import setup_process
from gpnerf_core.engine.validation import check_data

UNCOUNTED_FLOPS = ("its Gaussians are rasterized by numba kernels torch's FLOP counter cannot see (GFLOP/ray n/a; "
                   "the counted matmuls and convolutions are flops_torch_only)")
"""Why a rasterizing family's FLOPs are not reported (``Capabilities.gaussians``)."""

OUT_OF_MEMORY = ("OutOfMemoryError", "MemoryError", "out of memory", "can't allocate memory")
"""Markers of a child that ran out of memory (with a kill by signal 9)."""


def run_measurement(overrides: list[str], phase: str, warmup: int, repeats: int) -> dict[str, Any]:
    """One measurement in a child process; an error (out of memory included) comes back as ``{"error": ...}``."""
    with tempfile.TemporaryDirectory() as folder:
        progress = Path(folder) / "progress.json"
        spec = {"overrides": overrides, "phase": phase, "warmup": warmup, "repeats": repeats, "progress": str(progress)}
        done = subprocess.run(
            [sys.executable, "-m", "gpnerf_core.tools.bench.measure", json.dumps(spec)], capture_output=True, text=True
        )
        reached = json.loads(progress.read_text()) if progress.exists() else {}
    if done.returncode == 0:
        return json.loads(done.stdout.strip().splitlines()[-1])
    lines = [line for line in done.stderr.strip().splitlines() if line.strip()]
    last = lines[-1] if lines else f"exit code {done.returncode}"
    killed = done.returncode in (-9, 137)
    if killed or any(marker in done.stderr for marker in OUT_OF_MEMORY):
        peak = reached.get("peak_memory_mb")
        where = f"peak {peak:.0f} MiB after {reached.get('done', 0)} timed repetitions" if peak else "while building"
        return {"error": f"out of memory ({where})", "out_of_memory": True}
    return {"error": last}


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(run: Callable[[], Any], device: torch.device, warmup: int, repeats: int,
           progress: Path) -> tuple[list[float], float]:
    """Seconds of each of ``repeats`` runs after ``warmup`` runs, and the warm-up's seconds (``model.compile``
    compiles there); the peak memory goes to ``progress`` after each."""
    progress.write_text(json.dumps({"done": 0, "peak_memory_mb": peak_memory_mb(device)}))
    started = time.perf_counter()
    for _ in range(warmup):
        run()
    _synchronize(device)
    warmup_seconds = time.perf_counter() - started
    seconds = []
    for index in range(repeats):
        started = time.perf_counter()
        run()
        _synchronize(device)
        seconds.append(time.perf_counter() - started)
        progress.write_text(json.dumps({"done": index + 1, "peak_memory_mb": peak_memory_mb(device)}))
    return seconds, warmup_seconds


def count_flops(run: Callable[[], Any]) -> int:
    """Matmul and convolution flops of one run, forward and backward (torch's FLOP counter)."""
    with FlopCounterMode(display=False) as counter:
        run()
    return int(counter.get_total_flops())


def _flops(model: Any, run: Callable[[], Any]) -> dict[str, Any]:
    """``{"flops": n}``; for a family rasterizing Gaussians ``{"flops": None, "flops_note": why,
    "flops_torch_only": n}`` (the counter sees none of the rasterizer's work: 0 or a part would read as a figure)."""
    counted = count_flops(run)
    if model.capabilities.gaussians:
        return {"flops": None, "flops_note": UNCOUNTED_FLOPS, "flops_torch_only": counted}
    return {"flops": counted}


def measure(spec: dict[str, Any]) -> dict[str, Any]:
    cfg = compose(spec["overrides"])
    device = setup_process(cfg)
    components = build_components(cfg)
    check_data(cfg, components)
    progress = Path(spec["progress"])
    with tempfile.TemporaryDirectory() as folder:
        record = RunRecord(config_yaml="", overrides=(), components={})
        trainer = Trainer(cfg, components, dist=Distributed.single(device), run_dir=Path(folder), record=record)
        model = trainer.model
        result: dict[str, Any] = {
            "device": str(device),
            "torch_threads": torch.get_num_threads(),
            "parameters": {name: n for name, n in parameter_counts(model).items() if name != "total"},
            "samples_per_ray": (int(cfg.model.coarse_samples) + int(cfg.model.fine_samples)
                                if "coarse_samples" in cfg.model else None),  # None: a family without samples
        }
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        if spec["phase"] == "train":
            model.train()
            seconds, warmup_seconds = _timed(trainer.train_step, device, spec["warmup"], spec["repeats"], progress)
            rays = trainer.rays_per_view() * int(cfg.train.targets_per_step)  # every pixel for a whole-image family
            result.update(rays=rays, **_flops(model, trainer.train_step))
        else:
            model.eval()
            render = view_renderer(cfg, model, trainer.frames, trainer.sampler.selector, trainer.sampler.scene_names[0])
            seconds, warmup_seconds = _timed(render, device, spec["warmup"], spec["repeats"], progress)
            prediction = render()
            result.update(rays=int(prediction.rgb.shape[0] * prediction.rgb.shape[1]), **_flops(model, render))
    result.update(
        seconds=seconds,
        warmup_seconds=round(warmup_seconds, 3),
        seconds_median=statistics.median(seconds),
        seconds_min=min(seconds),
        peak_memory_mb=peak_memory_mb(device),
    )
    return result


def view_renderer(cfg: Any, model: Any, frames: FrameCache, selector: Any, scene_name: str) -> Callable[[], Any]:
    """``predict`` on the first held-out view of ``scene_name`` (a training scene), at the configured stride."""
    scene = frames.scene(scene_name)
    index = scene.eval_frames[0] if scene.eval_frames else scene.train_frames[0]
    sources = None
    if model.capabilities.generalizable:
        chosen = choose_sources(selector, scene, index, int(cfg.model.num_source_views), None)
        sources = frames.source_views(scene, chosen)
    frame = frames.frame(scene, index)
    camera = frames.camera(scene, frame)
    if model.capabilities.segments_image:  # a 2D model segments the real held-out image, as evaluation gives it
        camera = dataclasses.replace(camera, image=frame.rgb.to(frames.device))
    stride, chunk = int(cfg.eval.render_stride), int(cfg.eval.chunk_rays)
    return lambda: model.predict(camera, sources, stride=stride, chunk_rays=chunk)


if __name__ == "__main__":
    print(json.dumps(measure(json.loads(sys.argv[1]))))
