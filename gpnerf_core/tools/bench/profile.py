"""Where one training step's time goes: torch.profiler's operators, grouped by input shape, and the engine's stages.

    python -m gpnerf_core.tools.bench.profile [size=paper] [variant=gpnerf|gnt_only|both] [phase=train|render] [rows=30]
        [overrides like run's]

Builds the ``bench`` size's model (the GP-NeRF variant, its GNT-only anchor, or both one after the other), runs one
warm-up step, profiles the next one and prints the step time, the operators with the most self time, and the step
by stage (``gpnerf_core.runtime.profiling``: encoding, projection, transformers, semantic field, head, loss, optimizer; each
stage's forward and the backward of what its forward made). ``phase=render`` profiles the rendering of one held-out
view instead (``predict`` at ``eval.render_stride``, sources encoded each time, as ``bench`` renders). With
``variant=both`` the two stage tables are printed side by side: the semantic overhead stage by stage. The profiler adds overhead: read the shares, not the absolute
step time (``bench`` measures that). Stage times are CPU time on the calling thread (on CUDA: launch time).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from gpnerf_core.tools.bench.ab import phase_step
from gpnerf_core.tools.bench.sizes import VARIANTS, variant_overrides
from gpnerf_core.tools.bench.sizes import get_size
from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.errors import ConfigError
from gpnerf_core.runtime.profiling import StageTime, stage_table, stage_times
from gpnerf_core.model.checkpoint import RunRecord
from gpnerf_core.training.trainer import Trainer
from gpnerf_core.engine.setup import setup_process

OWN_KEYS = ("size", "variant", "phase", "rows")


def profile_step(overrides: list[str], rows: int, phase: str = "train") -> tuple[str, dict[str, StageTime]]:
    """The time and the profiler's table of one training step (or rendered view, ``phase=render``) after one
    warm-up, and its stage times."""
    cfg = compose(overrides)
    device = setup_process(cfg)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with tempfile.TemporaryDirectory() as folder:
        record = RunRecord(config_yaml="", overrides=(), components={})
        trainer = Trainer(cfg, build_components(cfg), dist=Distributed.single(device), run_dir=Path(folder), record=record)
        step = phase_step(trainer, phase)
        step()
        with profile(activities=activities, record_shapes=True) as profiler:
            started = time.perf_counter()
            step()
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            seconds = time.perf_counter() - started
    sort = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    table = profiler.key_averages(group_by_input_shape=True).table(
        sort_by=sort, row_limit=rows, max_name_column_width=32, max_shapes_column_width=80
    )
    what = "training step" if phase == "train" else "rendered view"
    text = f"one profiled {what}: {seconds:.2f} s on {device} ({torch.get_num_threads()} threads)\n{table}"
    return text, stage_times(profiler.events())


def main(argv: list[str]) -> int:
    own, overrides = {}, []
    for argument in argv:
        key, sep, value = argument.partition("=")
        (own.__setitem__(key, value) if sep and key in OWN_KEYS else overrides.append(argument))
    try:
        size = get_size(own.get("size", "paper"))
        variant = own.get("variant", "gpnerf")
        if variant not in (*VARIANTS, "both"):
            raise ConfigError(f"variant={variant!r} is unknown; known variants: {', '.join(VARIANTS)}, both")
        rows = int(own.get("rows", 30))
        phase = own.get("phase", "train")
        if phase not in ("train", "render"):
            raise ConfigError(f"phase={phase!r} is unknown; known phases: train, render")
        stages = {}
        for name in VARIANTS if variant == "both" else (variant,):
            text, stages[name] = profile_step(variant_overrides(size, name, overrides), rows, phase)
            print(f"== {name}\n{text}" if variant == "both" else text)
        what = "step" if phase == "train" else "rendered view"
        print(f"\none profiled {what} by stage (size={size.name}; each stage's forward, and the backward of what it made):")
        print(stage_table(stages))
    except (ConfigError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
