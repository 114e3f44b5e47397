"""Time one training step of the engine (sample, forward, loss, backward, optimizer step) and its peak memory."""

from __future__ import annotations

import resource
import statistics
import time
from pathlib import Path
from typing import Any

import torch

from gpnerf_core.engine.setup import setup_process
from gpnerf_core.model.build import build_components
from gpnerf_core.runtime.device import peak_memory_mb
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.model.checkpoint import RunRecord
from gpnerf_core.training.trainer import Trainer


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _resident_mb() -> float:
    """Current resident set size of this process in MiB (Linux /proc; falls back to the peak)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * resource.getpagesize() / 2**20
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def time_train_step(cfg: Any, *, warmup: int = 1, repeats: int = 3, run_dir: Path) -> dict[str, Any]:
    """Median and minimum seconds of ``repeats`` training steps after ``warmup`` steps, and peak memory.

    Returns:
        ``{"step_seconds_median", "step_seconds_min", "peak_memory_mb", "memory_before_mb", "rays_per_step",
        "device"}``; on CPU the memory is the process's peak RSS (``memory_before_mb``: RSS after building the
        model and loading the first batch's frames), on CUDA the peak allocated memory during the steps.
    """
    device = setup_process(cfg)
    record = RunRecord(config_yaml="", overrides=(), components={})
    trainer = Trainer(cfg, build_components(cfg), dist=Distributed.single(device), run_dir=run_dir, record=record)
    trainer.model.train()
    for _ in range(warmup):
        trainer.train_step()
    _synchronize(device)
    memory_before = _resident_mb() if device.type == "cpu" else torch.cuda.memory_allocated(device) / 2**20
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    seconds = []
    for _ in range(repeats):
        started = time.perf_counter()
        trainer.train_step()
        _synchronize(device)
        seconds.append(time.perf_counter() - started)
    return {
        "step_seconds_median": statistics.median(seconds),
        "step_seconds_min": min(seconds),
        "peak_memory_mb": peak_memory_mb(device),
        "memory_before_mb": memory_before,
        "rays_per_step": int(cfg.train.rays) * int(cfg.train.targets_per_step),
        "device": str(device),
    }
