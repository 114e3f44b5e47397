"""``python -m gpnerf_core fit [checkpoint=<generalizable run's .pt>] 'dataset.scenes=[<scene>]' [fit.*]``: one scene's
per-scene Gaussian model fitted until it has enough (docs/fit.md).

The family (``+experiment=baselines/semantic_3dgs`` unless another experiment is given; any family built on the public
``GaussianFamily``) starts from the scene's points as ``run`` starts it, or from a generalizable model's prediction
(``checkpoint=``: ``engine.fit_start.starting_point``), and trains on the scene's training frames until
``train.steps``, the training-seconds budget (``fit.seconds``), the target (``fit.target`` on ``fit.metric``) or a
plateau (``fit.patience``) stops it (``training.stopping``). Its held-out frames are evaluated at step 0 (the start,
before any training), every ``fit.eval_every`` steps and at the step it stops at: the curve, rewritten to
``fit_curve.json`` after each point and kept in ``metrics.json``'s ``fit`` section with why it stopped. The last point
is the run's usual final evaluation, so ``report`` reads a fit like any run.

Everything that can refuse the fit (the config, the family, the scene, the metric, read from the start's evaluation)
happens before the run folder is claimed.
"""

from __future__ import annotations

import sys
import time
from typing import Any

from omegaconf import DictConfig

from gpnerf_core.engine.fit_start import FitStart, apply_start, checkpoint_of, give_start, starting_point
from gpnerf_core.engine.guarding import job
from gpnerf_core.engine.launching import Handover, launch
from gpnerf_core.engine.resuming import plan_resume
from gpnerf_core.engine.runs import claim_run_folder, run_record, shared_run_dir, task_overrides
from gpnerf_core.engine.setup import start
from gpnerf_core.engine.validation import check_data
from gpnerf_core.errors import ConfigError
from gpnerf_core.evaluation.curves import check_fit_metric, curve_so_far, eval_scalars, fit_entry
from gpnerf_core.interfaces.model import parameter_counts
from gpnerf_core.runtime.device import machine_info
from gpnerf_core.runtime.distributed import Distributed
from gpnerf_core.runtime.io import atomic_write_json
from gpnerf_core.training.stopping import StopRules, Stopper

DEFAULT_EXPERIMENT = "baselines/semantic_3dgs"
"""The experiment ``fit`` composes when the command line gives none."""
CURVE_FILE = "fit_curve.json"
"""The curve's points evaluated so far, rewritten after each (a resumed fit keeps those up to its checkpoint)."""
HELD_OUT = "train_heldout"


def main(argv: list[str]) -> int:
    return launch(fit_task, with_default_experiment(argv), "gpnerf_core fit")


def with_default_experiment(argv: list[str]) -> list[str]:
    """``argv`` with ``+experiment=baselines/semantic_3dgs`` first where it chooses no experiment."""
    if any(a.lstrip("+~").startswith("experiment=") for a in argv) or "--help" in argv or "-h" in argv:
        return list(argv)
    return [f"+experiment={DEFAULT_EXPERIMENT}", *argv]


def gaussian_families() -> list[str]:
    """The registered model families that are per-scene Gaussian families (their config a ``GaussianSceneConfig``)."""
    from gpnerf_core.model.gaussian_config import GaussianSceneConfig
    from gpnerf_core.registry.components import get_registry

    models = get_registry().components["model"]
    return sorted(name for name, entry in models.items() if issubclass(entry.spec.config, GaussianSceneConfig))


def check_family(cfg: DictConfig) -> None:
    """Refuse a model that is not a per-scene Gaussian family, in one line naming those that are."""
    families = gaussian_families()
    if str(cfg.model.name) not in families:
        raise ConfigError(f"fit: model.name={cfg.model.name} is not a per-scene Gaussian family; expected one of "
                          f"{', '.join(families) or '(none registered)'} (default +experiment={DEFAULT_EXPERIMENT})")


def stop_rules(cfg: DictConfig) -> StopRules:
    """``fit.*`` as stop rules (``train.steps`` is the step budget, which ``Trainer.fit`` keeps)."""
    fit = cfg.fit
    return StopRules(metric=str(fit.metric), target=None if fit.target is None else float(fit.target),
                     patience=int(fit.patience), min_delta=float(fit.min_delta), seconds=float(fit.seconds or 0.0))


def curve_steps(every: int, total: int, after: int) -> list[int]:
    """The steps between the start and ``total`` (``train.steps``, evaluated as the last point) where the curve is
    evaluated: every ``every``-th (none for 0), after step ``after`` (a resumed fit's)."""
    return [step for step in range(every, total, every) if step > after] if every else []


@job
def fit_task(cfg: DictConfig, dist: Distributed, handover: Handover = Handover()) -> dict[str, Any]:
    from gpnerf_core.evaluation.evaluator import check_splits_have_frames, evaluate, print_summary
    from gpnerf_core.model.build import build_components
    from gpnerf_core.training.loggers import make_loggers
    from gpnerf_core.training.stopping import stopping_callback
    from gpnerf_core.training.trainer import Trainer

    start(cfg, validated=handover.validated)
    check_family(cfg)
    if list(cfg.eval.splits) != ["train"]:
        raise ConfigError(f"fit evaluates its scene's held-out frames: eval.splits=[{', '.join(cfg.eval.splits)}]; "
                          "expected eval.splits=[train]")
    rules = stop_rules(cfg)
    checkpoint = checkpoint_of(cfg)
    fit_start = FitStart() if checkpoint is None else starting_point(cfg, checkpoint, dist)
    cfg = apply_start(cfg, fit_start, list(task_overrides()))
    plan = plan_resume(cfg, dist)
    components = build_components(cfg)
    scenes = components.dataset.scenes("train")
    if len(scenes) != 1:
        listed = ", ".join(scenes[:4]) + (" ..." if len(scenes) > 4 else "")
        raise ConfigError(f"fit fits one scene: expected 'dataset.scenes=[<one scene>]'; dataset.scenes gives "
                          f"{len(scenes)}: {listed or 'none'}")
    scene = scenes[0]
    check_data(cfg, components, training=True)
    check_splits_have_frames(cfg, components)  # a stop rule on held-out frames that do not exist: refused here
    give_start(components.model, fit_start, tuple(components.classes.names) or None)
    record = run_record(cfg, components.model_sections)
    run_dir = shared_run_dir(cfg, dist)
    trainer = Trainer(cfg, components, dist=dist, run_dir=run_dir, record=record, resume_from=plan.take_read())
    family = components.model
    curve = curve_so_far(run_dir / CURVE_FILE, trainer.step, "fit") if plan.resuming else []
    stopper = Stopper(rules)
    for entry in curve:  # a resumed fit's rules see its earlier points again
        stopper.observe(int(entry["step"]), entry.get(rules.metric))

    weights = "trained"

    def evaluate_point(pictures: bool = False) -> dict[str, Any]:
        """Evaluate the held-out frames now; the point appended to the curve (replacing one at this step)."""
        nonlocal curve, weights
        with trainer.evaluation_weights() as weights:
            evaluation = evaluate(cfg, components, trainer.frames, run_dir, dist, pictures=pictures)
        held_out = evaluation["eval"].get(HELD_OUT, {})
        check_fit_metric(rules.metric, held_out, rules.reads_metric, scene)
        entry = fit_entry(trainer.step, trainer.training_seconds, fit_start.seconds, family.gaussians.size, held_out,
                          rules.metric)
        curve = [*(e for e in curve if e["step"] != entry["step"]), entry]
        return evaluation

    first = None
    if not curve or curve[-1]["step"] != trainer.step:  # the start (before the claim: it checks fit.metric)
        first = evaluate_point()
    else:
        check_fit_metric(rules.metric, {k: v for k, v in curve[-1].items() if k not in ("step", "gaussians")},
                         rules.reads_metric, scene)
    decision = stopper.observe(trainer.step, curve[-1].get(rules.metric)) if first is not None else stopper.decision
    folder, record = claim_run_folder(cfg, dist, resuming=plan.resuming, replace_leftovers=plan.replace_leftovers,
                                      record=record)
    with folder:
        loggers = make_loggers(list(cfg.train.loggers), run_dir, trainer.resumed_step) if dist.is_main else []
        try:
            started = time.perf_counter()

            def record_point(evaluation: dict[str, Any], say: bool = True) -> None:
                """The curve file rewritten, the point's scalars to the loggers and (``say``) one line."""
                if not dist.is_main:
                    return
                atomic_write_json(run_dir / CURVE_FILE, curve)
                for logger in loggers:
                    logger.log(trainer.step, eval_scalars(evaluation))
                if not say:
                    return
                shown = ", ".join(f"{key} {value:.3f}" for key, value in curve[-1].items()
                                  if "/" in key and isinstance(value, (int, float)))
                print(f"fit step {trainer.step} ({curve[-1]['seconds']:.1f} s, {curve[-1]['gaussians']} Gaussians): "
                      f"{shown}", file=sys.stderr)

            if dist.is_main:
                for note in (*fit_start.notes, *plan.notes, *trainer.notes):
                    print(f"note: {note}", file=sys.stderr)
                origin = f"checkpoint {fit_start.checkpoint}" if fit_start.kind == "checkpoint" else "its points"
                count = curve[0]["gaussians"] if curve else family.gaussians.size
                print(f"fit: scene {scene!r} from {origin} ({count} Gaussians); {_rules_text(cfg)}", file=sys.stderr)
            if first is not None:
                record_point(first)

            def evaluate_during(step: int) -> float | None:
                record_point(evaluate_point())
                return curve[-1].get(rules.metric)

            total = int(cfg.train.steps)
            callback = stopping_callback(stopper, curve_steps(int(cfg.fit.eval_every), total, trainer.step),
                                         evaluate_during)
            result = trainer.fit(until=trainer.step if decision is not None else None, progress=True,
                                 loggers=loggers, callbacks=[callback])
            if dist.is_main:
                atomic_write_json(run_dir / "training_curves.json", result.history)
            final_step = result.steps
            again = bool(curve) and curve[-1]["step"] == final_step  # a stop at a point: said already
            evaluation = evaluate_point(pictures=True)  # the run's final evaluation, the curve's last point
            record_point(evaluation, say=not again)
            stopped = stopper.decision
            reason = stopped.reason if stopped is not None else "steps"
            said = stopped.said if stopped is not None else f"steps (train.steps={total} reached)"
            start_gaussians = curve[0]["gaussians"] if curve else family.gaussians.size
            metrics = {
                "config_sha256": record.config_sha256,
                "seed": int(cfg.seed),
                "machine": machine_info(),
                "fit": {
                    "scene": scene,
                    "start": {"kind": fit_start.kind, "checkpoint": fit_start.checkpoint,
                              "gaussians": start_gaussians, "seconds": round(fit_start.seconds, 2),
                              "notes": list(fit_start.notes)},
                    "curve": curve,
                    "stopped": {"reason": reason, "step": final_step, "train_seconds": round(result.seconds, 2),
                                "said": said},
                },
                "train": result.metrics(cfg.train, dist.backend),
                "evaluated_weights": weights,
                "parameters": parameter_counts(family),
                **evaluation,
                "wall_seconds": round(time.perf_counter() - started, 2),
            }
            if dist.is_main:
                print(f"fit: stopped at step {final_step} after {result.seconds:.1f} s: {said}", file=sys.stderr)
                atomic_write_json(run_dir / "metrics.json", metrics)
                print_summary(metrics, run_dir)
        finally:
            for logger in loggers:
                logger.close()
    return metrics


def _rules_text(cfg: DictConfig) -> str:
    """The fit's budget and stop rules in words, for its first line."""
    fit = cfg.fit
    parts = [f"at most {int(cfg.train.steps)} steps"]
    if fit.seconds is not None:
        parts.append(f"{float(fit.seconds):g} training seconds")
    if fit.target is not None:
        parts.append(f"until {fit.metric} reaches {float(fit.target):g}")
    if int(fit.patience):
        parts.append(f"a plateau of {int(fit.patience)} evaluation(s) without a gain of {float(fit.min_delta):g}")
    every = int(fit.eval_every)
    cadence = f"evaluating every {every} steps" if every else "evaluating at the start and the end"
    return f"{', '.join(parts)}; {cadence}"
