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
import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from gpnerf_core.model.build import build_components
from gpnerf_core.config.compose import compose
from gpnerf_core.errors import ConfigError, GpnerfError
from gpnerf_core.runtime.io import atomic_write_json
from gpnerf_core.engine.setup import compose_checked, setup_process
from gpnerf_core.config.overrides import RUN_SPECIFIC_KEYS, override_key
from gpnerf_core.runtime.run_folder import LOCK_NAME, RunFolder
from gpnerf_core.tools.sizing.costs import StaticCost, static_cost
from gpnerf_core.tools.sizing.knobs import configured_knobs, knob_levels, label_of
from gpnerf_core.tools.sizing.options import SizeOptions, check_eval_splits, parse_size_options, resolve_metric
from gpnerf_core.tools.sizing.report import describe_scene, draw_trials, sized_command, write_experiment, write_report
from gpnerf_core.tools.sizing.scene import measure_scenes
from gpnerf_core.tools.sizing.search import (
    ReferenceFailed,
    Trial,
    choose,
    descend,
    describe,
    knob_order,
    refuse_unreachable_budgets,
)
from gpnerf_core.tools.sizing.trials import train_trial, with_bounds, with_changes
from gpnerf_core.engine.validation import check_data

OUTPUTS = ("size.md", "size.json", "scene.json", "speed_accuracy.png", "speed_accuracy.csv", "pareto.txt",
           "experiment", "runs", "request.json")
"""What a sizing writes into its folder; ``size.overwrite=true`` removes exactly these."""

class SizeFailed(GpnerfError):
    """No configuration meets the budgets (the report is still written)."""


def main(argv: list[str]) -> int:
    options, overrides = parse_size_options(argv)
    for argument in overrides:
        if override_key(argument) in RUN_SPECIFIC_KEYS:
            raise ConfigError(f"size: {argument!r} names a run's files; the sizing folder is size.out=<folder>")
        if argument.startswith("-"):
            raise ConfigError(f"size: {argument!r}: size takes Hydra overrides and size.<option>=<value>, not flags")
    cfg = compose_checked(overrides)
    model = build_components(cfg).model
    metric, tolerance = resolve_metric(options, model_predicts(model))
    if not model.capabilities.generalizable and not configured_knobs(cfg, per_scene=True):
        raise ConfigError(f"size: model {cfg.model.name!r} (per-scene) declares no size knob (size_knob on its config's "
                          "fields): nothing to size; declare one (docs/sizing.md) or train it as configured")
    if model.capabilities.gaussians and options.max_flops_per_ray:
        raise ConfigError(f"size.max_flops_per_ray={options.max_flops_per_ray:g}: model {cfg.model.name!r} rasterizes "
                          "Gaussians with numba kernels torch's FLOP counter cannot see; budget its time instead "
                          "(size.max_seconds_per_frame) or its size (size.max_parameters)")
    del model
    check_eval_splits(metric, list(cfg.eval.splits))
    steps = options.steps or max(1, int(cfg.train.steps) // 2)
    out = Path(options.out or Path("outputs") / "size" / time.strftime("%Y-%m-%d_%H-%M-%S"))
    request = {"overrides": overrides, **options.request(), "metric": metric, "tolerance": tolerance, "steps": steps,
               "coarse_samples": cfg.model.get("coarse_samples")}
    with RunFolder(out) as folder:
        folder.claim(resuming=True, overwrite=False)
        _check_request(out, request, options.overwrite)
        atomic_write_json(out / "request.json", request)
        try:
            return _size(cfg, overrides, options, metric, tolerance, steps, out)
        except GpnerfError as exc:
            if not isinstance(exc, SizeFailed) and not (out / "runs").exists():
                _forget_request(out)  # refused before any trial: a corrected request may use the folder
            raise


def model_predicts(model: Any) -> str | None:
    """What the built model's semantic scores are: ``classes``, ``instances``, or None (colour only)."""
    from gpnerf_core.interfaces.head import Predicts

    output = model.semantic_output
    return None if output is None else Predicts(output.predicts).value


def _forget_request(out: Path) -> None:
    """Remove what a sizing refused before its first trial wrote (its request and the scene measurement)."""
    for name in ("request.json", "scene.json"):
        (out / name).unlink(missing_ok=True)


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
    setup_process(cfg)
    components = build_components(cfg)
    check_data(cfg, components, training=True)
    per_scene = not components.model.capabilities.generalizable
    train_scenes = list(components.dataset.scenes("train"))
    print(f"measuring {len(train_scenes)} training scene(s) ...", flush=True)
    scene = measure_scenes(components.dataset, components.view_selector, scenes=train_scenes,
                           max_views=0 if per_scene else int(cfg.model.num_source_views), margin=options.depth_margin)
    atomic_write_json(out / "scene.json", scene.to_json())
    base, notes = with_bounds(overrides, scene)
    print(describe_scene(scene, cfg), flush=True)

    fewest = scene.fewest_views(options.min_coverage) if scene.coverage else 1
    if fewest is None:
        fewest = int(cfg.model.num_source_views)
        notes.append(f"no source-view count up to {fewest} shows {options.min_coverage:.0%} of a target's pixels to two "
                     "sources: source views not sized")
    reference_cfg = compose(base)
    levels, knob_notes = knob_levels(reference_cfg, fewest, per_scene=per_scene)
    notes += knob_notes
    if options.knobs:
        missing = [knob for knob in options.knobs if knob not in levels]
        if missing:  # a knob that cannot change this model would train the same model again and again
            reason = next((n.split(": ", 1)[1] for n in knob_notes if n.startswith(f"{missing[0]}:")),
                          "not one of size's knobs")
            raise ConfigError(f"size.knobs names {missing[0]}, which cannot be sized for model {cfg.model.name!r}: "
                              f"{reason}; knobs it can size: {', '.join(levels) or 'none'}")
        levels = {k: v for k, v in levels.items() if k in options.knobs}
    costs: dict[str, StaticCost] = {}

    def cost_of(changes: dict[str, int]) -> StaticCost:
        key = json.dumps(changes, sort_keys=True)
        if key not in costs:
            costs[key] = static_cost(compose(with_changes(base, changes)), train_scenes[0])
        return costs[key]

    budgets = options.budgets()
    refuse_unreachable_budgets(budgets, levels, cost_of)
    order = knob_order(levels, cost_of)
    total = 1 + sum(len(v[1]) for v in levels.values())
    print(f"sizing {len(levels)} knob(s) in this order: {', '.join(label_of(k) for k in order)}; at most {total} "
          f"trial(s) of {steps} steps x {options.seeds} seed(s); keep while {metric} >= reference - {tolerance}",
          flush=True)
    counter = iter(range(1, total + 1))

    def train(trial: Trial) -> None:
        train_trial(trial, base, steps, options.seeds, int(cfg.seed), metric, out, f"[{next(counter)}/{total}]")
        trained = trial.measured.get("parameters")
        if per_scene and trained:  # its size is what it trained to (built, it holds no Gaussians yet)
            trial.cost = replace(trial.cost, parameters=int(round(trained)))

    trials_so_far: list[Trial] = []

    def on_trial(trial: Trial, reference: Trial) -> None:
        verdict = "reference" if trial is reference else ("kept" if trial.kept else "not kept")
        shown = "failed: " + str(trial.error) if trial.accuracy is None else f"{metric} {trial.accuracy:.4f}"
        costs = (f", {trial.cost.parameters / 1e6:.3f} M parameters, {trial.cost.flops_text()} MFLOP/ray"
                 if trial.cost.rays else "")
        print(f"    {trial.name}: {shown}{costs} -> {verdict}", flush=True)
        trials_so_far.append(trial)
        write_report(out, scene, request_of(out), trials_so_far, None, None, notes, metric, tolerance)

    try:
        trials = descend(levels, order, cost_of, train, tolerance, on_trial)
    except ReferenceFailed as exc:
        raise GpnerfError(f"size: the reference configuration failed to train ({exc}); see {out / 'runs'}") from None
    chosen, failure = choose(trials, budgets)
    command = sized_command(base, chosen, out) if chosen else None
    if chosen is not None:
        write_experiment(out, chosen, base, metric, tolerance, trials[0], steps)
    write_report(out, scene, request_of(out), trials, chosen, command, notes, metric, tolerance, failure=failure)
    draw_trials(out, trials, chosen)
    print(f"\nsize.md: {(out / 'size.md').resolve()}")
    if chosen is None:
        raise SizeFailed(f"size: {failure} (every trial is in {out / 'size.md'})")
    reference = trials[0]
    flops = (f"{chosen.cost.flops_text()} MFLOP/ray (x{chosen.cost.flops_per_ray / reference.cost.flops_per_ray:.2f})"
             if chosen.cost.flops_counted and reference.cost.flops_per_ray else "MFLOP/ray n/a")
    params = (f" (x{chosen.cost.parameters / reference.cost.parameters:.2f})" if reference.cost.parameters else "")
    print(f"chosen: {describe(chosen.changes)}: {chosen.cost.parameters / 1e6:.3f} M parameters{params}, {flops}, "
          f"{metric} {chosen.accuracy:.4f} against {reference.accuracy:.4f}")
    print(f"run it: {command}")
    return 0


def request_of(out: Path) -> dict[str, Any]:
    return json.loads((out / "request.json").read_text())
