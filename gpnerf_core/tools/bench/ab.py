"""A/B of engine options inside one process: the variants alternate over training steps of one model, so both see
the same machine state (load, caches, frequency), which two processes one after the other do not.

    python -m gpnerf_core.tools.bench.ab [size=small] [rounds=4] [options=channels_last,compile,sampler] [threads=2]
        [phase=train|render] [depth_samples=C+F] [depth_sources=cost_volume,source_depth] [overrides...]

Prints per variant the minimum and median seconds of a training step (or of rendering one view, ``phase=render``) and the ratio of medians to the first variant; ``compile``
reports its compile time (the first steps of each new shape) apart from the steps timed. The options:

- ``channels_last``: ``model.channels_last_maps`` false against true (the same float32 values; the model attribute
  is switched between steps).
- ``compile``: the eager block pairs against ``torch.compile`` d ones (inductor).
- ``sampler``: ``model.sampler`` uniform against depth (``gpnerf_core.geometry.surface_depths``) from the coarse pass
  and from each of ``depth_sources`` (``+depth_source`` names: one pass, no coarse pass), the depth variants with
  ``depth_samples=C+F`` samples per ray (default: the configured counts).

The transformers' dropout (a plugin's internals) has its own script on top of ``alternate``: examples/ab_dropout.py.
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import torch

from gpnerf_core.tools.bench.sizes import get_size, variant_overrides
from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.engine.setup import setup_process
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.errors import ConfigError
from gpnerf_core.model.checkpoint import RunRecord
from gpnerf_core.training.trainer import Trainer

Variant = Callable[[Trainer], None]
"""Puts the trainer's model into one variant (called before each of its steps)."""


def channels_last_variants() -> dict[str, Variant]:
    def layout(flag: bool) -> Variant:
        return lambda trainer: setattr(trainer.model, "channels_last_maps", flag)

    return {"NCHW maps": layout(False), "channels-last maps": layout(True)}


def compile_variants(backend: str = "inductor") -> dict[str, Variant]:
    def use(on: bool) -> Variant:
        return lambda trainer: trainer.model.hooks.use_compiled(backend if on else None)

    return {"eager": use(False), f"compiled ({backend})": use(True)}


def sampler_variants(depth_samples: str, depth_sources: str = "") -> dict[str, Variant]:
    """``model.sampler`` uniform (the configured sample counts) against depth from the coarse pass and from each of
    ``depth_sources`` (comma-separated ``depth_source`` names: one pass, no coarse pass), with the counts
    ``depth_samples`` (``C+F``: coarse + fine; "" = the configured ones). The model is the same: only where it samples
    changes."""
    from gpnerf_core.registry.components import get_registry

    built = {name: get_registry().build("depth_source", {"name": name}) for name in depth_sources.split(",") if name}
    configured: dict[str, int] = {}

    def use(sampler: str, source: str | None = None) -> Variant:
        def switch(trainer: Trainer) -> None:
            model = trainer.model
            configured.setdefault("coarse", model.coarse_samples)
            configured.setdefault("fine", model.fine_samples)
            coarse, fine = configured["coarse"], configured["fine"]
            if sampler == "depth" and depth_samples:
                coarse, fine = _sample_counts(depth_samples)
            model.coarse_samples, model.fine_samples = coarse, fine
            model.sampling = dataclasses.replace(model.sampling, sampler=sampler)
            model.depth_source = built[source] if source else None
        return switch

    label = f"{depth_samples} samples, " if depth_samples else ""
    return {"uniform": use("uniform"), f"depth ({label}first pass)": use("depth"),
            **{f"depth ({label}{name})": use("depth", name) for name in built}}


def _sample_counts(text: str) -> tuple[int, int]:
    coarse, plus, fine = text.partition("+")
    if not (plus and coarse.isdigit() and fine.isdigit() and int(coarse) >= 2 and int(fine) >= 1):
        raise ConfigError(f"depth_samples={text!r}: expected C+F, coarse >= 2 and fine >= 1 samples per ray (e.g. 12+8)")
    return int(coarse), int(fine)


OPTIONS: dict[str, Callable[[dict[str, str]], dict[str, Variant]]] = {
    "channels_last": lambda settings: channels_last_variants(),
    "compile": lambda settings: compile_variants(),
    "sampler": lambda settings: sampler_variants(settings["depth_samples"], settings["depth_sources"]),
}


def make_trainer(size: str, overrides: list[str], folder: Path) -> Trainer:
    """A trainer of the bench ``size``'s GP-NeRF (``overrides`` last), writing nothing outside ``folder``."""
    cfg = compose(variant_overrides(get_size(size), "gpnerf", overrides))
    trainer = Trainer(cfg, build_components(cfg), dist=Distributed.single(setup_process(cfg)), run_dir=folder,
                      record=RunRecord(config_yaml="", overrides=(), components={}))
    trainer.model.train()
    return trainer


def phase_step(trainer: Trainer, phase: str) -> Callable[[], None]:
    """One unit of ``phase``: a training step, or (``render``) the prediction of one held-out view in eval mode
    (``eval.render_stride`` and ``eval.chunk_rays`` as configured), its sources encoded each time as ``bench`` does."""
    if phase == "train":
        def train() -> None:
            trainer.model.train()
            trainer.train_step()
        return train
    if phase == "render":
        view = trainer.sampler.next_batch().views[0]
        eval_cfg = trainer.cfg.eval

        def render() -> None:
            trainer.model.eval()
            trainer.model.predict(view.camera, view.sources, stride=int(eval_cfg.render_stride),
                                  chunk_rays=int(eval_cfg.chunk_rays))
        return render
    raise ConfigError(f"phase={phase!r}: expected train or render")


def alternate(trainer: Trainer, variants: dict[str, Variant], rounds: int,
              phase: str = "train") -> tuple[dict[str, list[float]], dict[str, float]]:
    """Seconds per ``phase`` unit per variant over ``rounds`` alternations, after warm-up units whose seconds
    (compilation, allocator growth) are returned apart: two per variant, so the coarse and fine shapes have both
    been seen."""
    step = phase_step(trainer, phase)
    warm_up = {}
    for name, variant in variants.items():
        started = time.perf_counter()
        for _ in range(2):
            variant(trainer)
            step()
        warm_up[name] = time.perf_counter() - started
    times: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, variant in variants.items():
            variant(trainer)
            started = time.perf_counter()
            step()
            times[name].append(time.perf_counter() - started)
    return times, warm_up


def timing_lines(times: dict[str, list[float]], warm_up: dict[str, float]) -> list[str]:
    first = statistics.median(next(iter(times.values())))
    lines = []
    for name, values in times.items():
        median = statistics.median(values)
        lines.append(f"  {name}: min {min(values):.3f} s, median {median:.3f} s, x{median / first:.2f} of the "
                     f"first; warm-up (2, compilation included) {warm_up[name]:.1f} s")
    return lines


def main(argv: list[str]) -> int:
    settings = {"size": "small", "rounds": "4", "options": "channels_last,compile", "threads": "2", "phase": "train",
                "depth_samples": "", "depth_sources": ""}
    overrides = []
    for argument in argv:
        key, _, value = argument.partition("=")
        if key in settings:
            settings[key] = value
        else:
            overrides.append(argument)
    options = [o for o in settings["options"].split(",") if o]
    unknown = [o for o in options if o not in OPTIONS]
    if unknown or not options:
        raise ConfigError(f"options={settings['options']!r}: expected a comma-separated list of {', '.join(OPTIONS)}")
    torch.set_num_threads(int(settings["threads"]))
    with tempfile.TemporaryDirectory() as folder:
        trainer = make_trainer(settings["size"], overrides, Path(folder))
        cfg = trainer.cfg
        print(f"bench.ab size={settings['size']} phase={settings['phase']}: {cfg.train.rays} rays, {cfg.model.get('coarse_samples')}+"
              f"{cfg.model.get('fine_samples')} samples, {cfg.model.num_source_views} views, {torch.get_num_threads()} threads, "
              f"{settings['rounds']} rounds, torch {torch.__version__}")
        for option in options:
            times, warm_up = alternate(trainer, OPTIONS[option](settings), int(settings["rounds"]), settings["phase"])
            print(f"{option}:")
            print("\n".join(timing_lines(times, warm_up)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
