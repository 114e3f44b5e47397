"""The refinement step: one training step of a per-scene Gaussian family (the experiment ``bench refine`` names) at a
given Gaussian count, timed part by part at each thread count in one process (``bench refine=<count>``).

A step is ``Trainer.train_step`` as ``run`` makes it: rasterize one 96 x 128 training view with SH colour and the
16-channel feature, decode by the 1 x 1 convolution, 0.8 L1 + 0.2 D-SSIM + cross-entropy, backward through the
rasterizer, gradient clipping (off) and Adam, and density control's statistics. The Gaussians start from the embedded
unseen layout's depth points (``unseen_00``, ``model.init_points`` = ``model.max_gaussians`` = the count); the run is
told ``train.steps=30000`` (the official schedule unscaled: no densification, pruning or opacity reset before step 500,
so every timed step has the same count) and ``model.sh_degree_every=1`` (the colour at its full degree 3 from the
third step, as in most of a fit's steps).

Parts (seconds, perf_counter marks at the trainer's callback phases): ``forward`` (sample, render, decode, loss and its
checks), ``backward`` (the rasterizer's and torch's backward, with the strategy's hook before it), ``density``
(density control's statistics: the ``after_backward`` callbacks), ``optimizer`` (clipping, Adam, the learning-rate
schedule) and ``checks`` (the ``after_step`` callbacks: the parameters' finiteness). Thread counts alternate step by
step after a warm-up at each, so a machine shared with other work disturbs them alike.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from gpnerf_core.errors import ConfigError
from gpnerf_core.interfaces.training import TrainingCallback, TrainingPhase

PARTS = ("forward", "backward", "density", "optimizer", "checks")
"""The parts of a step, in the order they run."""


def refine_overrides(count: int, experiment: str, overrides: list[str]) -> list[str]:
    """``run``'s overrides of the refinement step of ``experiment`` (a per-scene Gaussian family's) at ``count``
    Gaussians (the module docstring), then ``overrides``."""
    if count < 1:
        raise ConfigError(f"bench refine={count}: expected a Gaussian count >= 1")
    return [f"+experiment={experiment}", "dataset.scenes=[unseen_00]", f"model.init_points={count}",
            f"model.max_gaussians={count}", "train.steps=30000", "model.sh_degree_every=1", *overrides]


class _Marks:
    """perf_counter marks at the step's phases: the first callback of ``before_backward``, the first and the last
    of ``after_backward``, the first of ``after_step``."""

    def __init__(self) -> None:
        self.times: dict[str, float] = {}

    def mark(self, name: str) -> TrainingCallback:
        phase = {"forward": TrainingPhase.BEFORE_BACKWARD, "backward": TrainingPhase.AFTER_BACKWARD,
                 "density": TrainingPhase.AFTER_BACKWARD, "optimizer": TrainingPhase.AFTER_STEP}[name]
        return TrainingCallback(phase, lambda state: self.times.__setitem__(name, time.perf_counter()))


def _trainer(cfg: Any, folder: Path) -> Any:
    from gpnerf_core.engine.setup import setup_process
    from gpnerf_core.engine.validation import check_data
    from gpnerf_core.model.build import build_components
    from gpnerf_core.model.checkpoint import RunRecord
    from gpnerf_core.runtime.distributed import Distributed
    from gpnerf_core.training.trainer import Trainer

    device = setup_process(cfg)
    components = build_components(cfg)
    check_data(cfg, components)
    record = RunRecord(config_yaml="", overrides=(), components={})
    return Trainer(cfg, components, dist=Distributed.single(device), run_dir=folder, record=record)


def measure_refine(cfg: Any, threads: list[int], warmup: int, repeats: int) -> dict[str, Any]:
    """Median and minimum seconds of a step and of each of its ``PARTS`` at each of ``threads`` (torch's intra-op
    threads, which the numba rasterizer's pool follows), ``warmup`` steps at each first, then ``repeats`` rounds of one
    step per thread count."""
    with tempfile.TemporaryDirectory() as folder:
        trainer = _trainer(cfg, Path(folder))
        if not trainer.model.capabilities.gaussians:
            raise ConfigError(f"bench refine: model={cfg.model.name} rasterizes no Gaussians; expected a per-scene "
                              "Gaussian family")
        marks = _Marks()
        callbacks = trainer.callbacks
        callbacks[TrainingPhase.BEFORE_BACKWARD].insert(0, marks.mark("forward"))
        callbacks[TrainingPhase.AFTER_BACKWARD].insert(0, marks.mark("backward"))
        callbacks[TrainingPhase.AFTER_BACKWARD].append(marks.mark("density"))
        callbacks[TrainingPhase.AFTER_STEP].insert(0, marks.mark("optimizer"))
        trainer.model.train()
        count = trainer.model.gaussians.size

        def step(thread_count: int) -> dict[str, float]:
            torch.set_num_threads(thread_count)
            started = time.perf_counter()
            trainer.train_step()
            ended = time.perf_counter()
            trainer.step += 1
            times = marks.times
            return {"step": ended - started, "forward": times["forward"] - started,
                    "backward": times["backward"] - times["forward"], "density": times["density"] - times["backward"],
                    "optimizer": times["optimizer"] - times["density"], "checks": ended - times["optimizer"]}

        warmup_seconds = {}
        for thread_count in threads:
            started = time.perf_counter()
            for _ in range(warmup):
                step(thread_count)
            warmup_seconds[thread_count] = time.perf_counter() - started
        measured: dict[int, list[dict[str, float]]] = {thread_count: [] for thread_count in threads}
        for _ in range(repeats):
            for thread_count in threads:
                measured[thread_count].append(step(thread_count))
        counts = {"start": count, "end": trainer.model.gaussians.size, "steps": trainer.step}
    result: dict[str, Any] = {"gaussians": counts, "image": [int(cfg.dataset.height), int(cfg.dataset.width)],
                              "rasterizer": str(cfg.model.rasterizer), "threads": {}}
    for thread_count, rows in measured.items():
        result["threads"][str(thread_count)] = {
            "seconds": [row["step"] for row in rows],
            "seconds_median": statistics.median(row["step"] for row in rows),
            "seconds_min": min(row["step"] for row in rows),
            "parts_median": {part: statistics.median(row[part] for row in rows) for part in PARTS},
            "warmup_seconds": round(warmup_seconds[thread_count], 3),
        }
    return result


def format_refine(result: dict[str, Any]) -> str:
    """The table ``bench refine=`` prints: one row per thread count, milliseconds."""
    header = ("threads", "step ms (med/min)", *(f"{part} ms" for part in PARTS))
    rows = [header]
    for threads, entry in result["threads"].items():
        parts = entry["parts_median"]
        rows.append((threads, f"{entry['seconds_median'] * 1e3:.1f}/{entry['seconds_min'] * 1e3:.1f}",
                     *(f"{parts[part] * 1e3:.1f}" for part in PARTS)))
    widths = [max(len(str(row[i])) for row in rows) for i in range(len(header))]
    return "\n".join("  ".join(str(cell).rjust(widths[i]) for i, cell in enumerate(row)) for row in rows)
