"""Training the trials of a sizing: each in child ``run`` processes (one per seed, each its own peak memory) under
``<out>/runs``, reusing a finished run of exactly the same overrides; and the figures a trial's runs measured."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from gpnerf_core.config.overrides import RUN_SPECIFIC_KEYS, override_key
from gpnerf_core.tools.sizing.options import METRICS
from gpnerf_core.tools.sizing.scene import SceneMeasurement
from gpnerf_core.tools.sizing.search import Trial

MEASURED = {"held-out": "train_heldout", "unseen": "unseen"}
"""Splits whose accuracy a trial reports (name -> ``metrics.json`` split)."""




def with_bounds(overrides: list[str], scene: SceneMeasurement) -> tuple[list[str], list[str]]:
    """The overrides with the measured near/far added where the user set none."""
    if not scene.has_depth:
        return list(overrides), ["the frames carry no depth maps: near/far stay as configured"]
    given = {override_key(o) for o in overrides}
    added, notes = [], []
    for key, value in (("dataset.near", scene.near), ("dataset.far", scene.far)):
        if key in given:
            notes.append(f"{key} kept as given (measured: {value})")
        else:
            added.append(f"{key}={value}")
    return [*overrides, *added], notes


def with_changes(base: list[str], changes: dict[str, int]) -> list[str]:
    kept = [o for o in base if override_key(o) not in changes]
    return [*kept, *(f"{key}={value}" for key, value in changes.items())]


def train_trial(trial: Trial, base: list[str], steps: int, seeds: int, seed: int, metric: str, out: Path,
                 counter: str) -> None:
    """Train ``trial`` once per seed in child ``run`` processes (reusing finished runs of the same overrides)."""
    overrides = with_changes(base, trial.changes)
    slug = "reference" if not trial.changes else "_".join(f"{k.split('.')[-1]}{v}" for k, v in trial.changes.items())
    results: list[dict[str, Any]] = []
    for s in range(seed, seed + seeds):
        run_dir = out / "runs" / f"{slug}_s{s}"
        args = [*[o for o in overrides if override_key(o) != "seed"], f"seed={s}", f"train.steps={steps}",
                "eval.save_images=0"]
        metrics = _finished(run_dir, args)
        if metrics is None:
            print(f"{counter} {trial.name} (seed {s}): training {steps} steps ...", flush=True)
            metrics = _run(args, run_dir)
        if "error" in metrics:
            trial.error = metrics["error"]
            trial.runs.append(str(run_dir))
            return
        results.append(metrics)
        trial.runs.append(str(run_dir))
    split, key = METRICS[metric]
    values = [m.get("eval", {}).get(split, {}).get(key) for m in results]
    if any(v is None for v in values):
        trial.error = f"no {key} in {split} of metrics.json"
        return
    trial.accuracy = sum(values) / len(values)
    trial.measured = _measured(results)


def _finished(run_dir: Path, args: list[str]) -> dict[str, Any] | None:
    """The metrics of a finished run of exactly ``args`` in ``run_dir``, else None."""
    if not (run_dir / "metrics.json").is_file() or not (run_dir / "overrides.yaml").is_file():
        return None
    stored = OmegaConf.to_container(OmegaConf.load(run_dir / "overrides.yaml"))
    if sorted(o for o in stored if override_key(o) not in RUN_SPECIFIC_KEYS) != sorted(args):
        return None
    return json.loads((run_dir / "metrics.json").read_text())


def _run(args: list[str], run_dir: Path) -> dict[str, Any]:
    """``python -m gpnerf_core run <args>`` into ``run_dir`` (replacing an unfinished or different run there)."""
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "gpnerf_core", "run", *args, f"out_dir={run_dir}"]
    if run_dir.exists():
        command.append("overwrite=true")
    log = run_dir.parent / f"{run_dir.name}.log"
    with open(log, "w") as stream:
        done = subprocess.run(command, stdout=stream, stderr=subprocess.STDOUT)
    if done.returncode != 0 or not (run_dir / "metrics.json").is_file():
        lines = [line for line in log.read_text().splitlines() if line.startswith("error:")]
        return {"error": lines[-1][len("error: "):] if lines else f"exit code {done.returncode} (see {log})"}
    return json.loads((run_dir / "metrics.json").read_text())


def _measured(results: list[dict[str, Any]]) -> dict[str, float]:
    """Means over a trial's runs: held-out and unseen accuracy, training rays/s, s/frame and peak memory."""
    def mean(values: list[Any]) -> float | None:
        values = [float(v) for v in values if v is not None]
        return sum(values) / len(values) if values else None

    figures: dict[str, float | None] = {}
    for name, split in MEASURED.items():
        for metric, (_, key) in METRICS.items():
            figures[f"{metric} {name}"] = mean([m.get("eval", {}).get(split, {}).get(key) for m in results])
    timing = [m.get("eval", {}).get("train_heldout", {}).get("timing", {}) for m in results]
    figures["rays_per_second"] = mean([m.get("train", {}).get("rays_per_second") for m in results])
    figures["train_seconds"] = mean([m.get("train", {}).get("seconds") for m in results])
    figures["seconds_per_frame"] = mean([t.get("seconds_per_frame") for t in timing])
    figures["peak_memory_mb"] = mean([t.get("peak_memory_mb") for t in timing])
    figures["parameters"] = mean([(m.get("parameters") or {}).get("total") for m in results])  # as trained
    return {k: v for k, v in figures.items() if v is not None}
