"""The feature cache's target (issue 57): a provider's features of N frames computed once, a run's peak memory the same
at 100 and 1,000 frames (within 10 %), and a second run reading them without computing.

    python -m gpnerf_core.tools.bench.feature_cache [frames=100,1000] [provider=xfeat] [cache=DIR] [out=cache.json]
        [overrides...]

For each N, three fresh processes, each reporting its own peak resident memory (``ru_maxrss``): ``prepare`` loads the
scene (the embedded set renders its N frames once, outside the measurement), ``fill`` computes every frame into the
cache (a ``data features`` run), ``read`` is a run that reads every frame back in batches of 8 in a shuffled order, as
training draws them (it must compute nothing). The overrides are ``run``'s (default: one embedded scene of N frames
at 96 x 128, ``threads=1``); ``cache`` is the ``$GPNERF_CACHE`` folder (default: a temporary one, deleted after).
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

from gpnerf_core.runtime.io import atomic_write_json

PHASES = ("prepare", "fill", "read")
TOLERANCE = 0.10
"""The target: peak memory at the largest N within 10 % of the smallest N's."""


def scene_overrides(frames: int) -> list[str]:
    return ["dataset.num_train_scenes=1", "dataset.num_unseen_scenes=0", f"dataset.frames_per_scene={frames}",
            "dataset.eval_every=0", "dataset.height=96", "dataset.width=128", "threads=1"]


def _child(phase: str, provider: str, overrides: list[str]) -> None:
    """One phase in this process; prints one JSON line."""
    import time

    import torch

    from gpnerf_core.config.compose import compose
    from gpnerf_core.features import FeatureCache, build_feature_provider
    from gpnerf_core.registry.components import get_registry

    cfg = compose([f"+feature_provider={provider}", *overrides])
    torch.set_num_threads(max(1, int(cfg.threads)))
    dataset = get_registry().build("dataset", cfg.dataset)
    name = dataset.scenes("train")[0]
    scene = dataset.load_scene(name)
    record = {"phase": phase, "frames": scene.num_frames}
    started = time.perf_counter()
    if phase != "prepare":
        cache = FeatureCache(build_feature_provider(cfg), dataset, scene)
        if phase == "fill":
            cache.fill()
        else:
            order = torch.randperm(scene.num_frames, generator=torch.Generator().manual_seed(0)).tolist()
            for start in range(0, len(order), 8):
                cache.features(order[start:start + 8])
        record.update(computed=cache.computed, read=cache.read, folder=str(cache.folder),
                      shard_frames=cache.shard_frames,
                      cache_bytes=sum(p.stat().st_size for p in cache.folder.glob("shard_*.npy")))
    record.update(seconds=time.perf_counter() - started,
                  peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    print(json.dumps(record))


def measure(frames: list[int], provider: str, overrides: list[str], cache: Path) -> list[dict]:
    """Every phase at every N, each in a fresh process; the records in order."""
    env = {**os.environ, "GPNERF_CACHE": str(cache)}
    records = []
    for count in frames:
        for phase in PHASES:
            command = [sys.executable, "-m", "gpnerf_core.tools.bench.feature_cache", "--child", phase, provider,
                       *scene_overrides(count), *overrides]
            done = subprocess.run(command, env=env, capture_output=True, text=True)
            if done.returncode != 0:
                raise SystemExit(f"{phase} at {count} frames failed:\n{done.stderr[-3000:]}")
            records.append(json.loads(done.stdout.strip().splitlines()[-1]))
    return records


def verdict(records: list[dict]) -> list[str]:
    """The table's lines and the three targets, each PASS or FAIL."""
    lines = [f"{'frames':>7} {'phase':>8} {'computed':>9} {'read':>6} {'seconds':>8} {'peak MB':>8} {'cache MB':>9}"]
    for r in records:
        lines.append(f"{r['frames']:>7} {r['phase']:>8} {r.get('computed', ''):>9} {r.get('read', ''):>6} "
                     f"{r['seconds']:>8.2f} {r['peak_rss_mb']:>8.1f} {r.get('cache_bytes', 0) / 2**20:>9.1f}")
    fills = [r for r in records if r["phase"] == "fill"]
    reads = [r for r in records if r["phase"] == "read"]
    once = all(r["computed"] == r["frames"] for r in fills)
    no_recompute = all(r["computed"] == 0 and r["read"] == r["frames"] for r in reads)
    lines.append(f"{'PASS' if once else 'FAIL'}: every frame computed once by the fill")
    lines.append(f"{'PASS' if no_recompute else 'FAIL'}: the second run read every frame and computed none")
    for phase, rows in (("fill", fills), ("read", reads)):
        low, high = rows[0], rows[-1]
        growth = high["peak_rss_mb"] / low["peak_rss_mb"] - 1
        ok = abs(growth) <= TOLERANCE
        lines.append(f"{'PASS' if ok else 'FAIL'}: {phase} peak memory {low['peak_rss_mb']:.1f} MB at {low['frames']} "
                     f"frames, {high['peak_rss_mb']:.1f} MB at {high['frames']} ({growth:+.1%}; target within "
                     f"{TOLERANCE:.0%})")
    return lines


def main(argv: list[str]) -> int:
    if argv[:1] == ["--child"]:
        _child(argv[1], argv[2], argv[3:])
        return 0
    options = {"frames": "100,1000", "provider": "xfeat", "cache": "", "out": ""}
    overrides = []
    for arg in argv:
        key, _, value = arg.partition("=")
        if key in options:
            options[key] = value
        else:
            overrides.append(arg)
    frames = [int(n) for n in options["frames"].split(",") if n]
    with tempfile.TemporaryDirectory(prefix="gpnerf-feature-cache-") as scratch:
        cache = Path(options["cache"]) if options["cache"] else Path(scratch)
        records = measure(frames, options["provider"], overrides, cache)
    lines = verdict(records)
    print("\n".join(lines))
    if options["out"]:
        atomic_write_json(options["out"], {"records": records, "verdict": lines[-4:]})
    return 0 if all(not line.startswith("FAIL") for line in lines) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
