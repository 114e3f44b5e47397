"""fp32 vs bf16 vs activation checkpointing: step time and peak memory of one config, each in a fresh process.

    python -m gpnerf_core.tools.bench.precision +experiment=paper/gpnerf train.rays=128 [out=precision.json]

Every variant runs in its own subprocess so its peak memory is its own; the table goes to stdout, the figures to
``out`` (JSON) when given. The overrides are ``run``'s.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from gpnerf_core.runtime.io import atomic_write_json

VARIANTS = {
    "fp32": [],
    "bf16": ["train.precision=bf16"],
    "fp32 + checkpointed blocks": ["model.checkpoint_blocks=true"],
    "bf16 + checkpointed blocks": ["train.precision=bf16", "model.checkpoint_blocks=true"],
}


def _measure_one(overrides: list[str], warmup: int, repeats: int) -> None:
    """Child process: compose, time, print one JSON line."""
    from gpnerf_core.tools.bench.train_step import time_train_step
    from gpnerf_core.config.compose import compose

    cfg = compose(overrides)
    with tempfile.TemporaryDirectory() as folder:
        print(json.dumps(time_train_step(cfg, warmup=warmup, repeats=repeats, run_dir=Path(folder))))


def main(argv: list[str]) -> int:
    out = next((a.split("=", 1)[1] for a in argv if a.startswith("out=")), None)
    warmup = int(next((a.split("=", 1)[1] for a in argv if a.startswith("warmup=")), 1))
    repeats = int(next((a.split("=", 1)[1] for a in argv if a.startswith("repeats=")), 3))
    overrides = [a for a in argv if not a.startswith(("out=", "warmup=", "repeats="))]
    if not any(o.startswith(("+loss=", "+experiment=")) for o in overrides):
        overrides = ["+head=unet", "+loss=dgs", *overrides]
    results = {}
    for name, extra in VARIANTS.items():
        command = [sys.executable, "-m", "gpnerf_core.tools.bench.precision", "--child", str(warmup), str(repeats),
                   *overrides, *extra]
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            print(f"{name}: failed: {done.stderr.strip().splitlines()[-1] if done.stderr.strip() else done.returncode}")
            continue
        results[name] = json.loads(done.stdout.strip().splitlines()[-1])
    base = results.get("fp32")
    print(f"overrides: {' '.join(overrides)}")
    header = ("variant", "step s (median)", "min", "peak MiB", "vs fp32 time", "vs fp32 mem")
    print(f"{header[0]:<28} {header[1]:>16} {header[2]:>8} {header[3]:>10} {header[4]:>13} {header[5]:>12}")
    for name, r in results.items():
        time_ratio = r["step_seconds_median"] / base["step_seconds_median"] if base else float("nan")
        mem_ratio = r["peak_memory_mb"] / base["peak_memory_mb"] if base else float("nan")
        print(f"{name:<28} {r['step_seconds_median']:>16.3f} {r['step_seconds_min']:>8.3f} "
              f"{r['peak_memory_mb']:>10.0f} {time_ratio:>13.2f} {mem_ratio:>12.2f}")
    if out:
        atomic_write_json(out, {"overrides": overrides, "results": results})
    return 0 if len(results) == len(VARIANTS) else 1


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _measure_one(sys.argv[4:], int(sys.argv[2]), int(sys.argv[3]))
    else:
        sys.exit(main(sys.argv[1:]))
