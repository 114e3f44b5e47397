"""``python -m gpnerf_core size [Hydra overrides] [size.<option>=<value> ...]``: no more model than the scene needs.

1. Measure the training scenes (``sizing.scene``): depth range -> near/far (unless ``dataset.near``/``dataset.far`` are
   given), view overlap -> the fewest source views tried, pixel footprint (reported with each sample count's spacing).
2. Cost every configuration before training it (``sizing.costs``); refuse at once a parameter or FLOP budget that not
   even the smallest reachable configuration meets.
3. Descend (``sizing.search``) with short ``run`` s in child processes (each its own peak memory), one folder per run
   under ``<out>/runs``; a sizing killed and started again with the same request reuses every finished run.
4. Write ``size.md``, ``size.json``, ``speed_accuracy.png`` (every trial, chosen and reference marked) and
   ``experiment/sized.yaml``, which ``run hydra.searchpath=[file://<out>] +experiment=sized`` composes.
"""

from __future__ import annotations

import json
from dataclasses import replace
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from gpnerf_core.build import build_components
from gpnerf_core.config import compose
from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.io import atomic_write_json, atomic_write_text
from gpnerf_core.run import RUN_SPECIFIC_KEYS, override_key
from gpnerf_core.run_folder import LOCK_NAME, RunFolder
from gpnerf_core.sizing.costs import StaticCost, static_cost
from gpnerf_core.sizing.knobs import knob_levels, label_of
from gpnerf_core.sizing.options import METRICS, SizeOptions, parse_size_options, resolve_metric
from gpnerf_core.sizing.scene import SceneMeasurement, measure_scenes
from gpnerf_core.sizing.search import (
    ReferenceFailed,
    Trial,
    buildable_cost,
    choose,
    descend,
    describe,
    format_figure,
    format_option,
    knob_order,
    meets,
)
from gpnerf_core.validation import check_data, validate_config

OUTPUTS = ("size.md", "size.json", "scene.json", "speed_accuracy.png", "speed_accuracy.csv", "pareto.txt",
           "experiment", "runs", "request.json")
"""What a sizing writes into its folder; ``size.overwrite=true`` removes exactly these."""
MEASURED = {"held-out": "train_heldout", "unseen": "unseen"}
"""Splits whose accuracy a trial reports (name -> ``metrics.json`` split)."""


class SizeFailed(GpnerfError):
    """No configuration meets the budgets (the report is still written)."""


def main(argv: list[str]) -> int:
    options, overrides = parse_size_options(argv)
    for argument in overrides:
        if override_key(argument) in RUN_SPECIFIC_KEYS:
            raise ConfigError(f"size: {argument!r} names a run's files; the sizing folder is size.out=<folder>")
        if argument.startswith("-"):
            raise ConfigError(f"size: {argument!r}: size takes Hydra overrides and size.<option>=<value>, not flags")
    cfg = compose(overrides)
    validate_config(cfg)
    metric, tolerance = resolve_metric(options, cfg.get("head") is not None)
    steps = options.steps or max(1, int(cfg.train.steps) // 2)
    out = Path(options.out or Path("outputs") / "size" / time.strftime("%Y-%m-%d_%H-%M-%S"))
    request = {"overrides": overrides, **options.request(), "metric": metric, "tolerance": tolerance, "steps": steps,
               "coarse_samples": int(cfg.model.coarse_samples)}
    with RunFolder(out) as folder:
        folder.claim(resuming=True, overwrite=False)
        _check_request(out, request, options.overwrite)
        atomic_write_json(out / "request.json", request)
        return _size(cfg, overrides, options, metric, tolerance, steps, out)


def _check_request(out: Path, request: dict[str, Any], overwrite: bool) -> None:
    """A folder holding another request's sizing is refused (or cleared with ``size.overwrite=true``)."""
    previous = out / "request.json"
    others = [p.name for p in out.iterdir() if p.name not in (*OUTPUTS, LOCK_NAME)]
    if not previous.exists():
        if others:
            raise ConfigError(f"size.out={out} holds files a sizing does not write (first: {others[0]!r}); "
                              "choose another folder")
        return
    if json.loads(previous.read_text()) == request:
        return
    if not overwrite:
        raise ConfigError(f"size.out={out} holds a sizing of another request (request.json differs); "
                          "choose another folder or replace it with size.overwrite=true")
    for name in OUTPUTS:
        path = out / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def _size(cfg: Any, overrides: list[str], options: SizeOptions, metric: str, tolerance: float, steps: int,
          out: Path) -> int:
    import torch

    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    components = build_components(cfg)
    check_data(cfg, components, training=True)
    train_scenes = list(components.dataset.scenes("train"))
    print(f"measuring {len(train_scenes)} training scene(s) ...", flush=True)
    scene = measure_scenes(components.dataset, components.view_selector, scenes=train_scenes,
                           max_views=int(cfg.model.num_source_views), margin=options.depth_margin)
    atomic_write_json(out / "scene.json", scene.to_json())
    base, notes = _with_bounds(overrides, scene)
    print(describe_scene(scene, cfg), flush=True)

    fewest = scene.fewest_views(options.min_coverage) if scene.coverage else 1
    if fewest is None:
        fewest = int(cfg.model.num_source_views)
        notes.append(f"no source-view count up to {fewest} shows {options.min_coverage:.0%} of a target's pixels to two "
                     "sources: source views not sized")
    reference_cfg = compose(base)
    levels, knob_notes = knob_levels(reference_cfg, fewest)
    notes += knob_notes
    if options.knobs:
        levels = {k: v for k, v in levels.items() if k in options.knobs}
    costs: dict[str, StaticCost] = {}

    def cost_of(changes: dict[str, int]) -> StaticCost:
        key = json.dumps(changes, sort_keys=True)
        if key not in costs:
            costs[key] = static_cost(compose(with_changes(base, changes)), train_scenes[0])
        return costs[key]

    budgets = options.budgets()
    _refuse_unreachable_budgets(budgets, levels, cost_of)
    order = knob_order(levels, cost_of)
    total = 1 + sum(len(v[1]) for v in levels.values())
    print(f"sizing {len(levels)} knob(s) in this order: {', '.join(label_of(k) for k in order)}; at most {total} "
          f"trial(s) of {steps} steps x {options.seeds} seed(s); keep while {metric} >= reference - {tolerance}",
          flush=True)
    counter = iter(range(1, total + 1))

    def train(trial: Trial) -> None:
        _train_trial(trial, base, steps, options.seeds, int(cfg.seed), metric, out, f"[{next(counter)}/{total}]")

    trials_so_far: list[Trial] = []

    def on_trial(trial: Trial, reference: Trial) -> None:
        verdict = "reference" if trial is reference else ("kept" if trial.kept else "not kept")
        shown = "failed: " + str(trial.error) if trial.accuracy is None else f"{metric} {trial.accuracy:.4f}"
        costs = (f", {trial.cost.parameters / 1e6:.3f} M parameters, {trial.cost.flops_per_ray / 1e6:.2f} MFLOP/ray"
                 if trial.cost.rays else "")
        print(f"    {trial.name}: {shown}{costs} -> {verdict}", flush=True)
        trials_so_far.append(trial)
        _write_report(out, scene, request_of(out), trials_so_far, None, None, notes, metric, tolerance)

    try:
        trials = descend(levels, order, cost_of, train, tolerance, on_trial)
    except ReferenceFailed as exc:
        raise GpnerfError(f"size: the reference configuration failed to train ({exc}); see {out / 'runs'}") from None
    chosen, failure = choose(trials, budgets)
    command = sized_command(base, chosen, out) if chosen else None
    if chosen is not None:
        _write_experiment(out, chosen, base, scene, metric, tolerance, trials[0])
    _write_report(out, scene, request_of(out), trials, chosen, command, notes, metric, tolerance, failure=failure)
    _draw(out, trials, chosen)
    print(f"\nsize.md: {(out / 'size.md').resolve()}")
    if chosen is None:
        raise SizeFailed(f"size: {failure} (every trial is in {out / 'size.md'})")
    reference = trials[0]
    print(f"chosen: {describe(chosen.changes)}: "
          f"{chosen.cost.parameters / 1e6:.3f} M parameters (x{chosen.cost.parameters / reference.cost.parameters:.2f}), "
          f"{chosen.cost.flops_per_ray / 1e6:.2f} MFLOP/ray (x{chosen.cost.flops_per_ray / reference.cost.flops_per_ray:.2f}), "
          f"{metric} {chosen.accuracy:.4f} against {reference.accuracy:.4f}")
    print(f"run it: {command}")
    return 0


def request_of(out: Path) -> dict[str, Any]:
    return json.loads((out / "request.json").read_text())


def _with_bounds(overrides: list[str], scene: SceneMeasurement) -> tuple[list[str], list[str]]:
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


def _refuse_unreachable_budgets(budgets: dict[str, float], levels: dict[str, tuple[int, list[int]]],
                                cost_of: Any) -> None:
    """Parameter and FLOP budgets are known before training: refuse one not even every knob at its lowest meets."""
    static = {b: v for b, v in budgets.items() if b in ("max_parameters", "max_flops_per_ray")}
    if not static:
        return
    smallest = {key: smaller[-1] for key, (_, smaller) in levels.items()}
    cost = buildable_cost(cost_of, smallest)
    if not isinstance(cost, StaticCost):
        return  # the smallest corner cannot be built; the descent reports the budgets at the end
    trial = Trial("smallest", smallest, cost)
    failed = meets(trial, static)
    if failed:
        reached = ", ".join(f"{label_of(k)} {v}" for k, v in smallest.items()) or "the reference (no knob to turn)"
        values = {"max_parameters": f"{cost.parameters:,} parameters",
                  "max_flops_per_ray": f"{format_figure(cost.flops_per_ray)} FLOPs per ray"}
        raise ConfigError(
            "; ".join(f"size.{b}={format_option(static[b])}: no configuration the search can reach meets it "
                      f"(the smallest, {reached}, has {values[b]})" for b in failed)
        )


def _train_trial(trial: Trial, base: list[str], steps: int, seeds: int, seed: int, metric: str, out: Path,
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
    return {k: v for k, v in figures.items() if v is not None}


def describe_scene(scene: SceneMeasurement, cfg: Any) -> str:
    if not scene.has_depth:
        return f"  {scene.frames} frames, no depth maps: near/far stay {cfg.dataset.near} / {cfg.dataset.far} m"
    coverage = ", ".join(f"{v}: {c['2']:.0%}" for v, c in sorted(scene.coverage.items()))
    return (f"  {scene.frames} frames: depth {scene.depth_low} / {scene.depth_median} / {scene.depth_high} m "
            f"(percentiles {scene.percentiles[0]} / 50 / {scene.percentiles[1]}) -> near {scene.near} m, far "
            f"{scene.far} m (configured {cfg.dataset.near} / {cfg.dataset.far}); a pixel is "
            f"{scene.metres_per_pixel * 100:.1f} cm at the median depth; pixels two sources see, by sources: {coverage}")


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


def _write_experiment(out: Path, chosen: Trial, base: list[str], scene: SceneMeasurement, metric: str,
                      tolerance: float, reference: Trial) -> None:
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
        f" after {request_of(out)['steps']} steps),\n"
        f"# {chosen.cost.parameters:,} parameters and {chosen.cost.flops_per_ray / 1e6:.2f} MFLOP per ray against "
        f"{reference.cost.parameters:,} and {reference.cost.flops_per_ray / 1e6:.2f}.\n"
        f"# Run: {sized_command(base, chosen, out)}\n"
    )
    body = OmegaConf.to_yaml(OmegaConf.create(tree)) if tree else "{}\n"
    (out / "experiment").mkdir(exist_ok=True)
    atomic_write_text(out / "experiment" / "sized.yaml", header + body)


def _write_report(out: Path, scene: SceneMeasurement, request: dict[str, Any], trials: list[Trial],
                  chosen: Trial | None, command: str | None, notes: list[str], metric: str, tolerance: float,
                  failure: str | None = None) -> None:
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
            "flops_per_ray": trial.cost.flops_per_ray, "accuracy": trial.accuracy, "measured": trial.measured,
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
        spacing = "; ".join(
            f"{n}: {cm:.1f} cm apart at the median depth ({cm / (100 * scene.metres_per_pixel):.1f} pixel footprints)"
            for n in sorted({int(t.changes.get("model.coarse_samples", request["coarse_samples"])) for t in trials},
                            reverse=True)
            if (cm := sample_spacing_cm(scene, scene.near, scene.far, n)) is not None
        )
        lines += [
            f"- {scene.frames} frames of {len(scene.scenes)} scene(s); depth (percentiles {scene.percentiles[0]} / 50 / "
            f"{scene.percentiles[1]}): {scene.depth_low} / {scene.depth_median} / {scene.depth_high} m",
            f"- ray bounds: near {scene.near} m, far {scene.far} m (the range widened by {scene.margin:.0%})",
            f"- a pixel at the median depth: {scene.metres_per_pixel * 100:.2f} cm (focal {scene.focal_px} px)",
            f"- coarse samples over the measured bounds: {spacing}",
            "- target pixels seen by at least two of the V nearest sources: "
            + ", ".join(f"V={v}: {c['2']:.1%}" for v, c in sorted(scene.coverage.items())),
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
                 *((f"{trial.cost.parameters / 1e6:.3f}", f"{trial.cost.flops_per_ray / 1e6:.2f}") if trial.cost.rays
                   else ("", "")),
                 _cell(m.get("rays_per_second"), 0), _cell(m.get("seconds_per_frame"), 2), _cell(m.get("peak_memory_mb"), 0)]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    if chosen is not None and reference is not None:
        ratio = [
            f"parameters x{chosen.cost.parameters / reference.cost.parameters:.2f}",
            f"FLOPs per ray x{chosen.cost.flops_per_ray / reference.cost.flops_per_ray:.2f}",
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


def _draw(out: Path, trials: list[Trial], chosen: Trial | None) -> None:
    """Every trial on the speed-accuracy chart (FLOPs per ray among the costs), labelled by its whole configuration."""
    from gpnerf_core.report import RowGroup, find_runs
    from gpnerf_core.speed_accuracy import draw, methods_from_groups

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
