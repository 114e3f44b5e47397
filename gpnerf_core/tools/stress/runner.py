"""Evaluate trained models under every level of the chosen stress cases (``python -m gpnerf_core stress``).

For each model: the clean condition once (held-out views of the training scenes, the model's own source views),
then every level of every case. A level a dataset cannot offer is skipped with its reason; a non-finite metric is
recorded and fails the suite at the end (the suite guarantees no crash and no NaN).
"""

from __future__ import annotations

import copy
import hashlib
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import torch
import yaml
from omegaconf import DictConfig, open_dict

from gpnerf_core.errors import ConfigError, DataError, NonFiniteError, PluginError
from gpnerf_core.interfaces import StressCase

METRICS = {"miou": "miou/image_mean_present", "accuracy": "acc/image_total", "ap75": "instance/ap_matched@0.75",
           "psnr": "psnr/clamped"}
"""Figures kept per evaluation: name -> protocol id in ``metrics.json`` (mIoU and accuracy with a class head, matched
AP@0.75 with an instance head; PSNR always)."""

QUICK_VIEWS_PER_SCENE = 1
"""``--quick``: held-out views per scene evaluated (0 = all otherwise)."""


@dataclass(frozen=True)
class ModelUnderTest:
    """A trained model to stress: its checkpoint, composed config, method key and label.

    ``read``: the checkpoint as ``models_from_paths`` read it (a ``.pt`` given, the first model stressed), until the
    suite opens it (``take_read``): the file is not read twice, and nothing keeps its tensors afterwards.
    """

    checkpoint: Path
    config: dict[str, Any]
    method: str
    seed: Any
    name: str
    read: list[Any] = field(default_factory=list, repr=False, compare=False)

    def take_read(self) -> Any:
        """The checkpoint read (``TrainedModel``), handed over once; None when it was not kept."""
        return self.read.pop() if self.read else None


@dataclass
class Outcome:
    """One (model, case, level): its metrics, or why it was skipped."""

    model: str
    method: str
    seed: Any
    case: str
    level: float | None
    label: str
    metrics: dict[str, float] = field(default_factory=dict)
    skipped: str | None = None
    seconds: float = 0.0
    error: str | None = None
    """The evaluation stopped on a non-finite value (the metrics refuse NaN/Inf predictions)."""

    @property
    def non_finite(self) -> list[str]:
        found = [k for k, v in self.metrics.items() if not math.isfinite(v)]
        return found + ([self.error] if self.error else [])


def models_from_paths(paths: Sequence[Path]) -> list[ModelUnderTest]:
    """Run folders (or folders of runs) and ``.pt`` checkpoints, each a model; grouped into methods by config."""
    from gpnerf_core.model.trained import load_trained
    from gpnerf_core.tools.reporting.runs import RunRow, find_runs, group_runs, method_labels

    rows: list[RunRow] = []
    checkpoints: dict[Path, Path] = {}
    skipped: list[str] = []
    last = None  # the last checkpoint read: kept for the suite if it is the first model stressed
    for path in paths:
        if path.is_file():
            last = None  # one checkpoint's tensors at a time
            last = load_trained(path)
            row = RunRow(path.parent.parent if path.parent.name == "checkpoints" else path.parent,
                         yaml.safe_load(last.config_yaml) or {}, {})
            rows.append(row)
            checkpoints[row.folder] = path
            continue
        for row in find_runs([path]):
            checkpoint, reason = _usable_checkpoint(row)
            if checkpoint is None:
                skipped.append(f"{row.folder}: {reason}")
                print(f"stress: skipping {skipped[-1]}", file=sys.stderr)
                continue
            if reason:
                print(f"stress: note: {row.folder}: {reason}", file=sys.stderr)
            rows.append(row)
            checkpoints[row.folder] = checkpoint
    if not rows:
        why = f" (skipped {skipped[0]}{f'; {len(skipped) - 1} more above' if len(skipped) > 1 else ''})" if skipped else ""
        raise DataError(f"no trained runs or checkpoints under {', '.join(map(str, paths))}{why}")
    groups = group_runs(rows)
    labels = method_labels(groups)
    models = []
    for group, label in zip(groups, labels):
        for row in group.runs:
            models.append(ModelUnderTest(checkpoints[row.folder], row.config, label, row.config.get("seed"),
                                         row.folder.name))
    if last is not None and models[0].checkpoint == last.path:
        models[0].read.append(last)
    return models


def _usable_checkpoint(row: Any) -> tuple[Path | None, str]:
    """The checkpoint to stress of a ``find_runs`` row, with a note; or None and why the row is skipped.

    A finished run gives its final checkpoint. An unfinished one (no ``metrics.json``) whose newest checkpoint is at
    its ``train.steps`` finished training and stopped in evaluation: that checkpoint is the trained model. One that
    stopped earlier is a partly trained model, skipped (its checkpoint may be given as a path itself)."""
    from gpnerf_core.training.resume import run_checkpoints

    if row.state == "failed":
        return None, f"it failed ({row.error})"
    if row.state == "finished":
        checkpoint = _run_checkpoint(row.folder, row.metrics)
        return checkpoint, ("" if checkpoint is not None else
                            f"no checkpoint in {row.folder / 'checkpoints'} (an eval folder, or a copy without its "
                            "checkpoints)")
    found = run_checkpoints(row.folder)
    steps = (row.config.get("train") or {}).get("steps")
    if not found:
        return None, row.error
    step, newest = found[-1]
    if isinstance(steps, int) and step < steps:
        return None, (f"{row.error}; a partly trained model is not stressed unless its checkpoint is given: "
                      f"stress {newest} ...")
    return newest, f"{row.error}; stressing its final checkpoint {newest.name} (step {step})"


def _run_checkpoint(folder: Path, metrics: dict[str, Any]) -> Path | None:
    """The run's final checkpoint inside ``folder``: the one ``metrics.json`` names if the folder holds it, else its
    newest. A copied folder's ``metrics.json`` names the original's file, which is never taken in its place."""
    from gpnerf_core.training.resume import run_checkpoints

    recorded = (metrics.get("train") or {}).get("checkpoint")
    if recorded:
        own = folder / "checkpoints" / Path(str(recorded)).name
        if own.is_file():
            return own
    found = run_checkpoints(folder)
    return found[-1][1] if found else None


def choose_cases(names: Sequence[str] | None) -> list[StressCase]:
    """The registered cases named (all when None), in registration order; an unknown name lists the known."""
    from gpnerf_core.registry.components import clash_message, get_registry

    registered = {name: case for name, (case, _) in get_registry().stress_cases.items()}
    for key, providers in get_registry().clashes.items():  # two plugins' case of one name: neither runs silently
        if key.startswith("stress/") and (not names or key[len("stress/"):] in names):
            raise PluginError(clash_message(f"stress case {key[len('stress/'):]!r}", providers))
    if not names:
        return list(registered.values())
    unknown = [n for n in names if n not in registered]
    if unknown:
        raise ConfigError(f"unknown stress case {unknown[0]!r}; known cases: {', '.join(registered)}")
    return [registered[n] for n in dict.fromkeys(names)]


def _config(trained_config: DictConfig, views_per_scene: int, dataset_overrides: dict[str, Any]) -> DictConfig:
    """The trained model's config (``open_trained``'s) for evaluation, with the dataset overrides."""
    cfg = copy.deepcopy(trained_config)
    with open_dict(cfg):
        cfg.eval.max_views_per_scene = views_per_scene
        cfg.eval.save_images = 0
        for key, value in dataset_overrides.items():
            cfg.dataset[key] = value
    return cfg


class _Evaluator:
    """One model, its weights loaded once; datasets (and frame caches) per dataset variant."""

    def __init__(self, model: ModelUnderTest, views_per_scene: int, device: torch.device, threads: int) -> None:
        from gpnerf_core.engine.opening import open_trained
        from gpnerf_core.model.trained import load_trained

        self.model = model
        self.views_per_scene = views_per_scene
        self.device = device
        opened = open_trained(model.take_read() or load_trained(model.checkpoint),
                              [f"device={device.type}", f"threads={threads}"], command="stress", weights="average",
                              device=device)
        self.trained_config = opened.cfg
        self.cfg = _config(self.trained_config, views_per_scene, {})
        self.components = opened.components
        self.components.model.eval()
        self._variants: dict[str, tuple[DictConfig, Any, Any]] = {}

    def variant(self, overrides: dict[str, Any]) -> tuple[DictConfig, Any, Any]:
        """``(cfg, components, frames)`` with the dataset changed by ``overrides`` (shared model)."""
        from dataclasses import replace

        from gpnerf_core.data.frames import FrameCache
        from gpnerf_core.registry.components import get_registry

        key = repr(sorted(overrides.items()))
        if key not in self._variants:
            cfg = _config(self.trained_config, self.views_per_scene, overrides)
            components = self.components
            if overrides:
                components = replace(components, dataset=get_registry().build("dataset", cfg.dataset))
            self._variants[key] = (cfg, components, FrameCache(components.dataset, self.device))
        return self._variants[key]

    def evaluate(self, case: StressCase | None, level: float | None, run_dir: Path) -> dict[str, float]:
        from gpnerf_core.runtime.distributed import Distributed
        from gpnerf_core.evaluation.evaluator import evaluate
        from gpnerf_core.data.frames import choose_sources

        overrides = case.dataset_overrides(level, self.cfg.dataset) if case is not None else {}
        cfg, components, frames = self.variant(overrides)
        split = case.split if case is not None else "train"
        with open_dict(cfg):
            cfg.eval.splits = [split]
        trained_views = int(cfg.model.num_source_views)

        def choose(scene, target: int, count: int) -> list[int]:
            return choose_sources(components.view_selector, scene, target, count, None)

        def targets_for(scene) -> list[int]:
            return case.target_frames(level, scene, list(scene.eval_frames))

        def sources_for(scene, target: int):
            if not components.model.capabilities.generalizable:
                return None  # a per-scene model renders from its own parameters
            if case is None:
                return frames.source_views(scene, choose(scene, target, trained_views))
            count = case.num_source_views(level, trained_views)
            indices = case.source_indices(level, scene, target, count, choose)
            if target in indices or len(indices) != count:
                raise DataError(f"stress case {case.name!r} level {level:g}: gave sources {indices} for target "
                                f"{target} of {scene.name!r}; expected {count} frames, not the target")
            generator = torch.Generator().manual_seed(_seed(case.name, level, scene.name, target))
            return case.perturb_sources(level, frames.source_views(scene, indices), generator)

        changes_targets = case is not None and changes_target_frames(case)
        result = evaluate(cfg, components, frames, run_dir, Distributed.single(), sources_for=sources_for,
                          targets_for=targets_for if changes_targets else None, references=False)
        label = "train_heldout" if split == "train" else "unseen"
        values = result["eval"][label]
        return {name: float(values[key]) for name, key in METRICS.items() if values.get(key) is not None}

    def scenes(self, case: StressCase, level: float) -> list[Any]:
        cfg, components, frames = self.variant(case.dataset_overrides(level, self.cfg.dataset))
        return [frames.scene(name) for name in components.dataset.scenes(case.split)]


def _seed(*parts: Any) -> int:
    """A generator seed fixed by (case, level, scene, target): the same suite perturbs the same way."""
    return int.from_bytes(hashlib.sha256(repr(parts).encode()).digest()[:8], "little") >> 1


def run_suite(
    models: list[ModelUnderTest], cases: list[StressCase], *, quick: bool, views_per_scene: int, scratch: Path,
    device: torch.device, threads: int = 0, outcomes: list[Outcome] | None = None,
) -> list[Outcome]:
    """Every model under the clean condition and every chosen level of every case, with progress on stderr.

    Args:
        device, threads: where and with how many torch threads (0: torch's default) every model is evaluated.
        outcomes: the list each finished evaluation is appended to as it ends (so an interrupted suite's caller still
            holds them); a new one when None.
    """
    outcomes = [] if outcomes is None else outcomes
    for model in models:
        evaluator = _Evaluator(model, views_per_scene, device, threads)
        started = time.perf_counter()
        clean = evaluator.evaluate(None, None, scratch)
        outcomes.append(Outcome(model.name, model.method, model.seed, "clean", None, "clean", clean,
                                seconds=time.perf_counter() - started))
        print(f"stress: {model.name} clean: {_shown(clean)}", file=sys.stderr)
        first = len(outcomes)
        for case in cases:
            for level in case.chosen_levels(quick):
                outcome = Outcome(model.name, model.method, model.seed, case.name, float(level), case.label(level))
                reason = _unavailable(case, level, evaluator)
                if reason is not None:
                    outcome.skipped = reason
                    shown = f"skipped: {reason}"
                else:
                    started = time.perf_counter()
                    try:
                        outcome.metrics = evaluator.evaluate(case, level, scratch)
                    except NonFiniteError as exc:
                        outcome.error = str(exc)
                    outcome.seconds = time.perf_counter() - started
                    shown = _shown(outcome.metrics) if outcome.error is None else f"NOT FINITE: {outcome.error}"
                outcomes.append(outcome)  # before its line: an interruption after the line keeps what it reports
                print(f"stress: {model.name} {case.name} {case.label(level)}: {shown}", file=sys.stderr)
        note = no_case_applies(evaluator, cases, outcomes[first:])
        if note is not None:
            print(f"stress: note: {model.name}: {note}", file=sys.stderr)
    return outcomes


def no_case_applies(evaluator: "_Evaluator", cases: list[StressCase], outcomes: list[Outcome]) -> str | None:
    """One line when every level of every chosen case was skipped for a model (None otherwise): for a per-scene
    model, the registered cases that do apply to it."""
    if any(not o.skipped for o in outcomes):
        return None
    if evaluator.components.model.capabilities.generalizable:
        return f"none of the {len(cases)} chosen case(s) applies to it (each skip's reason is in stress.md); clean only"
    from gpnerf_core.registry.components import get_registry

    applying = [name for name, (case, _) in get_registry().stress_cases.items() if per_scene_applies(case)]
    offer = (f"the cases that change only which held-out views are scored apply: --cases {','.join(applying)}"
             if applying else "no registered case changes only the held-out views scored")
    return (f"model {evaluator.cfg.model.name!r} is per-scene (no source views, its own scene only): none of the "
            f"{len(cases)} chosen case(s) applies to it; clean only; {offer}")


def dataset_options(name: str) -> set[str]:
    """The config fields of the registered dataset ``name``."""
    import dataclasses

    from gpnerf_core.registry.components import get_registry

    registered = get_registry().components["dataset"].get(name)
    return {f.name for f in dataclasses.fields(registered.spec.config)} if registered else set()


def changes_sources(case: StressCase) -> bool:
    """The case changes the source views a model is given (which, how many, their images or cameras)."""
    return any(getattr(type(case), method) is not getattr(StressCase, method)
               for method in ("source_indices", "num_source_views", "perturb_sources"))


def changes_target_frames(case: StressCase) -> bool:
    """The case changes which held-out target views are scored."""
    return type(case).target_frames is not StressCase.target_frames


def per_scene_applies(case: StressCase) -> bool:
    """The case can run on a per-scene model: it changes which held-out views of the model's own scene are scored
    and nothing else (no source views, no dataset variant, no other split). A case with ``dataset_overrides`` is
    judged per level by the suite."""
    return changes_target_frames(case) and not changes_sources(case) and case.split == "train" \
        and type(case).dataset_overrides is StressCase.dataset_overrides


def _unavailable(case: StressCase, level: float, evaluator: _Evaluator) -> str | None:
    """Why the level cannot run: the model has no source views to change, a dataset option its variant needs is
    missing, or the case's own reason."""
    per_scene = not evaluator.components.model.capabilities.generalizable
    if changes_sources(case) and per_scene:
        return (f"model {evaluator.cfg.model.name!r} renders from its own parameters (per-scene): it has no source "
                "views to change")
    dataset = evaluator.cfg.dataset
    if per_scene and (case.split != "train" or case.dataset_overrides(level, dataset)):
        return (f"model {evaluator.cfg.model.name!r} is fitted on its own scene's frames (per-scene): another scene, or "
                "its scene re-rendered, is not its to render (it would be scored against frames it never modelled)")
    options = dataset_options(str(dataset.get("name")))
    missing = [key for key in case.dataset_overrides(level, dataset) if key not in options]
    if missing:
        return f"dataset {dataset.get('name')!r} has no option {missing[0]!r} for this variant ({case.description})"
    scenes = evaluator.scenes(case, level)
    reason = case.unavailable(level, dataset, scenes, int(evaluator.cfg.model.num_source_views))
    if reason is None and not any(scene.eval_frames for scene in scenes):
        reason = f"no evaluation frames in the {case.split!r} split"
    return reason


def _shown(metrics: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.3f}" for k, v in metrics.items())
