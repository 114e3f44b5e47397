"""What a sizing writes: ``size.md`` and ``size.json`` (the scene, every trial, the choice), the chosen configuration
as ``experiment/sized.yaml`` with the command that runs it, and every trial on the speed-accuracy chart."""

from __future__ import annotations

import shlex
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from gpnerf_core.runtime.io import atomic_write_json, atomic_write_text
from gpnerf_core.config.overrides import override_key
from gpnerf_core.tools.sizing.scene import SceneMeasurement
from gpnerf_core.tools.sizing.search import Trial, describe


def describe_scene(scene: SceneMeasurement, cfg: Any) -> str:
    if not scene.has_depth:
        return f"  {scene.frames} frames, no depth maps: near/far stay {cfg.dataset.near} / {cfg.dataset.far} m"
    coverage = ", ".join(f"{v}: {c['2']:.0%}" for v, c in sorted(scene.coverage.items()))
    return (f"  {scene.frames} frames: depth {scene.depth_low} / {scene.depth_median} / {scene.depth_high} m "
            f"(percentiles {scene.percentiles[0]} / 50 / {scene.percentiles[1]}) -> near {scene.near} m, far "
            f"{scene.far} m (configured {cfg.dataset.near} / {cfg.dataset.far}); a pixel is "
            f"{scene.metres_per_pixel * 100:.1f} cm at the median depth"
            + (f"; pixels two sources see, by sources: {coverage}" if coverage else " (per-scene: no source views)"))


def sample_spacing_cm(scene: SceneMeasurement, near: float, far: float, samples: int) -> float | None:
    """Spacing of ``samples`` inverse-depth samples at the median depth, cm (d^2 * step in 1/depth)."""
    if scene.depth_median is None or samples < 2:
        return None
    step = (1.0 / near - 1.0 / far) / (samples - 1)
    return 100.0 * scene.depth_median**2 * step


def sized_command(base: list[str], chosen: Trial, out: Path) -> str:
    """The ``run`` command for the chosen configuration: the request's overrides that the file does not set, and the
    file through Hydra's search path."""
    written = {"dataset.near", "dataset.far", *chosen.changes}
    kept = [o for o in base if override_key(o) not in written]
    args = ["run", *kept, f"hydra.searchpath=[file://{out.resolve()}]", "+experiment=sized"]
    return "python -m gpnerf_core " + " ".join(shlex.quote(a) for a in args)


def write_experiment(out: Path, chosen: Trial, base: list[str], metric: str, tolerance: float, reference: Trial,
                     steps: int) -> None:
    """``experiment/sized.yaml``: the measured near/far and the chosen knob values, and how it was chosen."""
    values: dict[str, Any] = {}
    for item in base:
        key, _, value = item.partition("=")
        if key in ("dataset.near", "dataset.far"):
            values[key] = float(value)
    values.update(chosen.changes)
    tree: dict[str, Any] = {}
    for key, value in values.items():
        node = tree
        *parents, leaf = key.split(".")
        for parent in parents:
            node = node.setdefault(parent, {})
        node[leaf] = value
    header = (
        "# @package _global_\n"
        f"# Written by `python -m gpnerf_core size` ({time.strftime('%Y-%m-%d %H:%M')}): the cheapest configuration\n"
        f"# kept within {tolerance} {metric} of the reference ({chosen.accuracy:.4f} against {reference.accuracy:.4f}"
        f" after {steps} steps),\n"
        f"# {chosen.cost.parameters:,} parameters and {chosen.cost.flops_text()} MFLOP per ray against "
        f"{reference.cost.parameters:,} and {reference.cost.flops_text()}.\n"
        f"# Run: {sized_command(base, chosen, out)}\n"
    )
    body = OmegaConf.to_yaml(OmegaConf.create(tree)) if tree else "{}\n"
    (out / "experiment").mkdir(exist_ok=True)
    atomic_write_text(out / "experiment" / "sized.yaml", header + body)


def write_report(out: Path, scene: SceneMeasurement, request: dict[str, Any], trials: list[Trial],
                 chosen: Trial | None, command: str | None, notes: list[str], metric: str, tolerance: float,
                 failure: str | None = None) -> None:
    """``size.json`` and ``size.md`` (rewritten after every trial, so a killed sizing shows how far it got)."""
    atomic_write_json(out / "size.json", {
        "request": request,
        "scene": scene.to_json(),
        "notes": notes,
        "trials": [_trial_json(t) for t in trials],
        "chosen": chosen.name if chosen else None,
        "command": command,
        "failure": failure,
    })
    atomic_write_text(out / "size.md", format_report(scene, request, trials, chosen, command, notes, metric,
                                                     tolerance, failure))


def _trial_json(trial: Trial) -> dict[str, Any]:
    return {"name": trial.name, "changes": trial.changes, "parameters": trial.cost.parameters,
            "flops_per_ray": trial.cost.flops_per_ray if trial.cost.flops_counted else None, "accuracy": trial.accuracy, "measured": trial.measured,
            "kept": trial.kept, "error": trial.error, "runs": trial.runs}


def format_report(scene: SceneMeasurement, request: dict[str, Any], trials: list[Trial], chosen: Trial | None,
                  command: str | None, notes: list[str], metric: str, tolerance: float, failure: str | None) -> str:
    reference = trials[0] if trials else None
    lines = ["# Sizing", "", "```", "python -m gpnerf_core size " + " ".join(
        [*map(shlex.quote, request["overrides"]),
         *(f"size.{k}={v}" for k, v in request.items()
           if k not in ("overrides", "coarse_samples") and v not in ("", [], 0, 0.0))]),
        "```", "", "## The scene (training frames only)", ""]
    if scene.has_depth:
        samples = [] if request.get("coarse_samples") is None else sorted(  # a ray-marching family's only
            {int(t.changes.get("model.coarse_samples", request["coarse_samples"])) for t in trials}, reverse=True)
        spacing = "; ".join(
            f"{n}: {cm:.1f} cm apart at the median depth ({cm / (100 * scene.metres_per_pixel):.1f} pixel footprints)"
            for n in samples
            if (cm := sample_spacing_cm(scene, scene.near, scene.far, n)) is not None
        )
        lines += [
            f"- {scene.frames} frames of {len(scene.scenes)} scene(s); depth (percentiles {scene.percentiles[0]} / 50 / "
            f"{scene.percentiles[1]}): {scene.depth_low} / {scene.depth_median} / {scene.depth_high} m",
            f"- ray bounds: near {scene.near} m, far {scene.far} m (the range widened by {scene.margin:.0%})",
            f"- a pixel at the median depth: {scene.metres_per_pixel * 100:.2f} cm (focal {scene.focal_px} px)",
            *([f"- coarse samples over the measured bounds: {spacing}"] if samples else []),
            *(["- target pixels seen by at least two of the V nearest sources: "
               + ", ".join(f"V={v}: {c['2']:.1%}" for v, c in sorted(scene.coverage.items()))] if scene.coverage
              else []),
        ]
    else:
        lines.append(f"- {scene.frames} frames; no depth maps, so the configured near/far were kept")
    lines += [f"- note: {n}" for n in notes]
    lines += ["", f"## Trials ({request['steps']} steps x {request['seeds']} seed(s); kept while {metric} >= "
              f"reference - {tolerance})", ""]
    header = ["trial", "configuration", "kept", f"{metric} held-out", "mIoU unseen", "PSNR held-out", "parameters (M)", "MFLOP/ray",
              "train rays/s", "s/frame", "peak MB"]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for trial in trials:
        m = trial.measured
        mark = " (chosen)" if trial is chosen else ""
        kept = "reference" if trial is reference else ("yes" if trial.kept else "no")
        accuracy = "failed: " + str(trial.error) if trial.accuracy is None else f"{trial.accuracy:.4f}"
        cells = [trial.name + mark, describe(trial.changes), kept, accuracy, _cell(m.get("miou unseen"), 4), _cell(m.get("psnr held-out"), 2),
                 *((f"{trial.cost.parameters / 1e6:.3f}", trial.cost.flops_text()) if trial.cost.rays
                   else ("", "")),
                 _cell(m.get("rays_per_second"), 0), _cell(m.get("seconds_per_frame"), 2), _cell(m.get("peak_memory_mb"), 0)]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    if chosen is not None and reference is not None:
        ratio = [
            f"parameters x{chosen.cost.parameters / reference.cost.parameters:.2f}" if reference.cost.parameters
            else "parameters n/a",
            f"FLOPs per ray x{chosen.cost.flops_per_ray / reference.cost.flops_per_ray:.2f}"
            if reference.cost.flops_counted and reference.cost.flops_per_ray else "FLOPs per ray n/a",
        ]
        if chosen.measured.get("seconds_per_frame") and reference.measured.get("seconds_per_frame"):
            ratio.append(f"s/frame x{chosen.measured['seconds_per_frame'] / reference.measured['seconds_per_frame']:.2f}")
        lines += [f"**Chosen: {describe(chosen.changes)}** ({', '.join(ratio)} of the "
                  f"reference; {metric} {chosen.accuracy:.4f} against {reference.accuracy:.4f}).", "",
                  "```", command or "", "```", "",
                  "The accuracy of a short run of one seed is noisy: train the chosen configuration and the reference "
                  "at the full recipe over several seeds before relying on the difference."]
    elif failure:
        lines.append(f"**No configuration chosen**: {failure}.")
    return "\n".join(lines) + "\n"


def _cell(value: float | None, digits: int) -> str:
    return "" if value is None else f"{value:.{digits}f}"


def draw_trials(out: Path, trials: list[Trial], chosen: Trial | None) -> None:
    """Every trial on the speed-accuracy chart (FLOPs per ray among the costs), labelled by its whole configuration."""
    from gpnerf_core.tools.reporting.runs import RowGroup, find_runs
    from gpnerf_core.tools.reporting.speed_accuracy import draw, methods_from_groups

    groups, labels = [], []
    for trial in trials:
        rows = [row for path in trial.runs if Path(path).is_dir() for row in find_runs([Path(path)])]
        if not rows or trial.accuracy is None:
            continue
        rows = [replace(row, metrics={**row.metrics, "flops_per_ray": trial.cost.flops_per_ray}) for row in rows]
        groups.append(RowGroup(tuple(rows)))
        labels.append(describe(trial.changes) + (" (chosen)" if trial is chosen else ""))
    if groups:
        draw(methods_from_groups(groups, labels), out)
