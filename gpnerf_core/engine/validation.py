"""Refuse bad config values, and data a run cannot train on, before any work is done.

Each refusal is one line naming the key (or the scene, or the file), the value and what is expected. Component
options are checked by the components themselves when they are built, which also happens before any work.
"""

from __future__ import annotations

import dataclasses
import math
import re
import sys
import typing
from typing import Any, Callable

from omegaconf import DictConfig, OmegaConf

from gpnerf_core.features.field import FeatureFieldOptions
from gpnerf_core.model.build import Components
from gpnerf_core.config.schema import RootConfig
from gpnerf_core.data.checks import pose_warnings
from gpnerf_core.runtime.device import PRECISIONS
from gpnerf_core.errors import ConfigError, DataError
from gpnerf_core.interfaces.head import Predicts
from gpnerf_core.registry.components import get_registry
from gpnerf_core.registry.kinds import KINDS
from gpnerf_core.training.optimizer import learning_rates
from gpnerf_core.training.schedule import LR_SCHEDULES
from gpnerf_core.model.checkpoint import WEIGHT_CHOICES
from gpnerf_core.training.loggers import check_loggers


def _count(minimum: int) -> Callable[[Any], bool]:
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= minimum


def _positive(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0


def _non_negative(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _fraction(v: Any) -> bool:
    return _positive(v) and v <= 1


def _port(v: Any) -> bool:
    return _count(0)(v) and v <= 65535


def _ema_decay(v: Any) -> bool:
    return _non_negative(v) and v < 1


MAX_SEED = 2**63 - 1
"""torch.manual_seed's largest seed that every seeded stream here (torch, numpy, the samplers' hashes) accepts."""
MAX_THREADS = 1024
"""More threads than any machine here has cores; beyond it OpenMP fails to start them (a traceback, not a run)."""
COUNT = "an integer >= 1"
COUNT0 = "an integer >= 0"
RULES: tuple[tuple[str, Callable[[Any], bool], str], ...] = (
    ("device", lambda v: isinstance(v, str) and re.fullmatch(r"auto|cpu|cuda(:\d+)?", v) is not None,
     "auto, cpu or cuda[:N]"),
    ("seed", lambda v: _count(0)(v) and v <= MAX_SEED, f"an integer in [0, {MAX_SEED}]"),
    ("threads", lambda v: _count(0)(v) and v <= MAX_THREADS, f"an integer in [0, {MAX_THREADS}] (0 = torch's default)"),
    ("train.steps", _count(1), COUNT),
    ("train.rays", _count(1), COUNT),
    ("train.targets_per_step", _count(1), COUNT),
    ("train.lr_decay_rate", _fraction, "a factor in (0, 1]"),
    ("train.lr_decay_steps", _count(1), COUNT),
    ("train.warmup_steps", _count(0), f"{COUNT0} (0 = no warm-up)"),
    ("train.grad_clip", _non_negative, "a finite norm >= 0 (0 = off)"),
    ("train.ema_decay", _ema_decay, "a decay in [0, 1) (0 = no weight average)"),
    ("train.log_every", _count(1), COUNT),
    ("train.checkpoint_every", _count(0), f"{COUNT0} (0 = only the final checkpoint)"),
    ("train.keep_checkpoints", _count(0), f"{COUNT0} (0 = keep every checkpoint)"),
    ("model.coarse_samples", _count(2), "an integer >= 2"),  # a ray-marching family's (RayMarchingConfig) only
    ("model.fine_samples", _count(0), f"{COUNT0} (0 = one pass)"),
    ("model.num_source_views", _count(0), f"{COUNT0} (0 only for a per-scene family: it reads no source views)"),
    ("eval.render_stride", _count(0), f"{COUNT0} (0 = the semantic map's stride)"),
    ("eval.chunk_rays", _count(1), COUNT),
    ("eval.max_views_per_scene", _count(0), f"{COUNT0} (0 = all)"),
    ("eval.save_images", _count(0), COUNT0),
    ("eval.every_steps", _count(0), f"{COUNT0} (0 = only at the end of training)"),
    ("fit.eval_every", _count(0), f"{COUNT0} (training steps between evaluations; 0 = only the start and the end)"),
    ("fit.seconds", lambda v: v is None or (_positive(v) and _finite(v)),
     "null (no budget) or a finite training-seconds budget > 0"),
    ("fit.target", lambda v: v is None or _finite(v), "null or a finite value of fit.metric"),
    ("fit.metric", lambda v: isinstance(v, str) and v != "", "a metric name of the held-out frames "
     "(miou/image_mean_present; psnr/clamped on a scene without labels)"),
    ("fit.patience", _count(0), f"{COUNT0} (evaluations without a gain before a stop; 0 = no plateau rule)"),
    ("fit.min_delta", _non_negative, "a finite gain >= 0 of fit.metric"),
    ("fit.start_every", _count(1), f"{COUNT} (every k-th training frame gives the start)"),
    ("fit.start_opacity", lambda v: _positive(v) and v < 1, "an opacity in (0, 1)"),
    ("fit.start_budget", _count(0), f"{COUNT0} (Gaussians a start keeps; 0 = model.max_gaussians)"),
    ("fit.start_min_views", _count(0), f"{COUNT0} (other frames that must agree with a start's Gaussian)"),
    ("fit.start_conflicts", _count(0), f"{COUNT0} (other frames that may see through a start's Gaussian)"),
    ("fit.start_tolerance", lambda v: _positive(v) and v < 1, "a relative depth tolerance in (0, 1)"),
    ("fit.start_geometry", lambda v: v in ("predicted", "points"), "predicted or points (where a start's Gaussians "
     "stand: the model's depth, or the scene's own points)"),
    ("fit.start_semantics", lambda v: isinstance(v, bool), "true or false"),
    ("view.port", _port, "a TCP port in [0, 65535] (0 = any free port)"),
    ("view.stride", _count(1), COUNT),
    ("view.preview_stride", _count(1), COUNT),
    ("view.source_views", _count(0), f"{COUNT0} (0 = model.num_source_views)"),
    ("view.feature_cache_mb", _non_negative, "megabytes >= 0 (0 = no feature cache)"),
    ("export.every", _count(1), COUNT),
    ("export.stride", _count(0), f"{COUNT0} (0 = eval.render_stride)"),
    ("export.min_views", _count(0), f"{COUNT0} (0 = keep every point inside the depth bounds)"),
    ("export.tolerance", _positive, "a finite relative depth difference > 0"),
    ("export.voxel", _non_negative, "a finite side in metres >= 0 (0 = no merging)"),
)
"""(key, check, what is expected) for every numeric key of the schema (``gpnerf_core/config/schema.py``)."""

FAMILY_KEYS = {"model.coarse_samples": "coarse_samples", "model.fine_samples": "fine_samples"}
"""Keys of ``RULES`` that only some model families have (checked where the family's config has them)."""

SPLITS = ("train", "unseen")


def validate_config(cfg: DictConfig) -> None:
    """Refuse unknown keys (also those added with ``+``) and out-of-range values of the schema's keys."""
    _refuse_unknown_keys(cfg, RootConfig, "")
    for key, check, expected in RULES:
        if key in FAMILY_KEYS and FAMILY_KEYS[key] not in cfg.model:
            continue
        value = OmegaConf.select(cfg, key)
        if not check(value):
            raise ConfigError(f"{key}={value!r}: expected {expected}")
    if cfg.train.lr_schedule not in LR_SCHEDULES:
        raise ConfigError(f"train.lr_schedule={cfg.train.lr_schedule!r}: expected one of {', '.join(LR_SCHEDULES)}")
    if cfg.eval.weights not in WEIGHT_CHOICES:
        raise ConfigError(f"eval.weights={cfg.eval.weights!r}: expected one of {', '.join(WEIGHT_CHOICES)}")
    if cfg.train.precision not in PRECISIONS:
        raise ConfigError(f"train.precision={cfg.train.precision!r}: expected one of {', '.join(PRECISIONS)}")
    learning_rates(cfg.model.get("lr"))  # every model.lr.<group>: a finite rate > 0
    family = _component_config("model", cfg.model)
    if cfg.model.num_source_views == 0 and family is not None and family().num_source_views > 0:
        raise ConfigError(f"model.num_source_views=0: model {cfg.model.name!r} renders from source views; expected an "
                          "integer >= 1 (0 only for a per-scene family)")
    _check_fit_cadence(cfg)
    bad_splits = [s for s in cfg.eval.splits if s not in SPLITS]
    if bad_splits:
        raise ConfigError(f"eval.splits contains {bad_splits[0]!r}; expected some of {', '.join(SPLITS)}")
    check_loggers(list(cfg.train.loggers))
    FeatureFieldOptions.from_config(cfg.get("features"))  # features.*: its values, with or without a provider


def _check_fit_cadence(cfg: DictConfig) -> None:
    """A stop rule on the held-out metric (``fit.target``, ``fit.patience``) needs evaluations during the fit."""
    if int(cfg.fit.eval_every) > 0:
        return
    for key, value, unset in (("fit.patience", cfg.fit.patience, 0), ("fit.target", cfg.fit.target, None)):
        if value != unset:
            raise ConfigError(f"{key}={value}: a stop rule on the held-out metric needs evaluations while fitting, but "
                              f"fit.eval_every=0; expected fit.eval_every >= 1 (training steps between evaluations)")


def _refuse_unknown_keys(node: DictConfig, schema: type, prefix: str, component: bool = False) -> None:
    """``component``: ``node`` is a component's section, whose unknown options ``Registry.build`` refuses itself,
    listing the component's options; its nested sections are checked here."""
    hints = typing.get_type_hints(schema)
    fields = {f.name for f in dataclasses.fields(schema)}
    for key in node.keys():
        path = f"{prefix}{key}"
        if component and key not in fields:
            continue
        if key not in fields:
            raise ConfigError(
                f"unknown config key {path!r}; {schema.__name__} has: {', '.join(sorted(fields))} "
                "(a key added with '+' must still be one the schema knows)"
            )
        if key == "hydra":
            continue
        hint = hints.get(key)
        child = node.get(key)
        if key in KINDS and (not component or KINDS[key].part):
            # A component's options (a part's under the model's): its registered config (an unknown top-level option
            # is also refused when it is built, naming the options; here nested ones are too, before any work).
            hint = _component_config(key, child)
            if hint is None or not isinstance(child, DictConfig):
                continue
            _refuse_unknown_keys(child, hint, f"{path}.", component=True)
            continue
        if dataclasses.is_dataclass(hint) and isinstance(child, DictConfig):
            _refuse_unknown_keys(child, hint, f"{path}.")


def _component_config(kind: str, node: Any) -> type | None:
    """The config dataclass of the component ``node`` names (None: not a registered name; the build refuses it)."""
    name = node.get("name") if isinstance(node, DictConfig) else None
    entry = get_registry().components.get(kind, {}).get(str(name))
    return entry.spec.config if entry is not None else None


def check_data(cfg: DictConfig, components: Components, *, training: bool = True) -> None:
    """Check the dataset's files (at ``dataset.validate``) and that every scene offers enough source views."""
    dataset = components.dataset
    configured = (OmegaConf.select(cfg, "dataset.height"), OmegaConf.select(cfg, "dataset.width"))
    if all(isinstance(side, int) and side > 0 for side in configured):  # before any scene is loaded (or rendered)
        check_image_size(cfg, components, *configured, f"dataset.height x dataset.width = {configured[0]}x{configured[1]}")
    _require_one_scene(cfg, components, training)
    splits = ["train"] if training else []
    splits += [s for s in cfg.eval.splits if s not in splits]
    scenes = list(dict.fromkeys(name for split in splits for name in dataset.scenes(split)))
    level = dataset.validation
    problems = dataset.check_files(scenes, level)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise DataError(
            f"dataset.validate={level} found {len(problems)} problem(s) before training; first: {problems[0]}{more}"
        )
    for note in pose_warnings(dataset, scenes, level):  # outlier, isolated or turned-away cameras: train, but say so
        print(f"note: {note}", file=sys.stderr)
    _require_labels(cfg, components, training)
    _require_trained_head(cfg, components, training)
    _require_instances(cfg, components, scenes, training)
    views = int(cfg.model.num_source_views)
    if components.model.capabilities.generalizable and views < 1:
        raise ConfigError(f"model.num_source_views={views}: expected an integer >= 1 (model={cfg.model.name} renders "
                          "from source views)")
    training_scenes = set(dataset.scenes("train")) if training else set()
    for name in scenes:
        scene = dataset.load_scene(name)
        check_image_size(cfg, components, scene.height, scene.width, f"scene {name!r} ({scene.height}x{scene.width})")
        pixels = scene.height * scene.width
        if name in training_scenes and int(OmegaConf.select(cfg, "train.rays", default=0)) > pixels:
            raise ConfigError(f"train.rays={int(cfg.train.rays)} exceeds the {pixels} pixels of an image of scene "
                              f"{name!r} ({scene.height}x{scene.width}); expected at most {pixels} rays per target view")
        train = set(scene.train_frames)
        offered = len(train) - 1 if name in training_scenes or train & set(scene.eval_frames) else len(train)
        if components.model.capabilities.generalizable and offered < views:
            raise ConfigError(
                f"model.num_source_views={views} but scene {name!r} offers {offered} source views per target "
                f"({len(train)} training frames, never the target itself); expected model.num_source_views <= {offered}"
            )


def _require_one_scene(cfg: DictConfig, components: Components, training: bool) -> None:
    """A per-scene family (``Capabilities.generalizable`` False) is fitted on one scene's frames and scores only that
    scene's held-out frames: training on several scenes would fit one field to all of them, and another scene is not
    its to render."""
    if components.model.capabilities.generalizable:
        return
    name = cfg.model.name
    if training:
        scenes = components.dataset.scenes("train")
        if len(scenes) != 1:
            listed = ", ".join(scenes[:4]) + (" ..." if len(scenes) > 4 else "")
            raise ConfigError(f"model={name} is fitted per scene: expected one training scene "
                              f"('dataset.scenes=[<name>]'); the dataset gives {len(scenes)}: {listed or 'none'}")
    if "unseen" in cfg.eval.splits:
        raise ConfigError(f"model={name} is fitted per scene and renders only that scene: eval.splits="
                          f"[{', '.join(cfg.eval.splits)}] asks for unseen scenes; expected eval.splits=[train] (its "
                          "held-out frames)")


def check_image_size(cfg: DictConfig, components: Components, height: int, width: int, where: str) -> None:
    """The model can render (and encode) ``height`` x ``width`` images and a non-zero ``eval.render_stride`` divides
    both."""
    try:
        components.model.check_image_size(int(height), int(width))
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    stride = int(OmegaConf.select(cfg, "eval.render_stride", default=0))
    if stride and (height % stride or width % stride):
        raise ConfigError(f"eval.render_stride={stride} does not divide the image size of {where}; expected a "
                          "divisor of both sides (0 = the semantic map's stride)")


def _require_trained_head(cfg: DictConfig, components: Components, training: bool) -> None:
    """Semantic outputs trained from scratch need a loss set that renders semantics (``LossSet.needs_semantics``):
    otherwise no term reaches them and their evaluation would score an untrained head. A model that starts trained
    (``finetune``'s checkpoint, ``model.init``) may keep them fixed, and a family whose own loss terms are weighted
    (``Capabilities.loss_terms``, ``model.loss_weights``) trains them itself."""
    from gpnerf_core.training.trainer import family_term_weights

    output, loss = components.model.semantic_output, components.loss
    if not training or output is None or loss is None or loss.needs_semantics:
        return
    if cfg.get("checkpoint") or cfg.model.get("init"):
        return
    if family_term_weights(str(cfg.model.name), components.model, cfg.model.get("loss_weights")):
        return
    raise ConfigError(
        f"{_scores_owner(cfg)} is trained by no term of loss {cfg.loss.name!r} (it renders no semantics), so its "
        "scores would be an untrained head's; use a loss set with semantic terms (e.g. +loss=dgs) or drop +head"
    )


def _require_labels(cfg: DictConfig, components: Components, training: bool) -> None:
    """A loss set that reads labels (``LossSet.needs_labels``, True unless it says otherwise) trains on no scene without
    labels (``Scene.labelled`` False): its labels are all ignored, so its label terms would silently be zero."""
    loss = components.loss
    if not training or loss is None or not getattr(loss, "needs_labels", True):
        return
    for name in components.dataset.scenes("train"):
        if not components.dataset.load_scene(name).labelled:
            raise ConfigError(
                f"scene {name!r} has no labels, but loss {cfg.loss.name!r} trains on labels; train without labels "
                "with +loss=label_free (colour + distillation from the 2D teacher)"
            )


INSTANCE_FRAMES_CHECKED = 8
"""Training frames per scene (spread over the scene) whose instance count is checked against ``head.slots``."""


def _require_instances(cfg: DictConfig, components: Components, scenes: list[str], training: bool) -> None:
    """An instance head (or a loss set that trains one) needs instance ids in every labelled scene it trains or
    evaluates on (the first frame of each scene is looked at; a scene without labels is only rendered), and before
    training at most ``head.slots`` ids in a frame (checked on ``INSTANCE_FRAMES_CHECKED`` frames per training scene;
    the loss names any other frame that has more)."""
    output = components.model.semantic_output
    needs = (training and components.loss is not None and components.loss.needs_instances) or (
        output is not None and output.predicts is Predicts.INSTANCES
    )
    if not needs:
        return
    for name in scenes:
        scene = components.dataset.load_scene(name)
        if not scene.labelled:
            continue
        first = (scene.train_frames or scene.eval_frames)[0]
        if scene.load_frame(first).instance is None:
            raise ConfigError(
                f"dataset {cfg.dataset.name!r} has no instance ids (scene {name!r}, frame {first}), but "
                f"{_scores_owner(cfg)} predicts instances; use a dataset with instance ids (embedded, replica_instance, "
                f"replica with semantic_instance/ folders, scannet with instance-filt/ folders)"
            )
    slots = output.slots if output is not None else None
    if not training or not isinstance(slots, int):
        return
    for name in components.dataset.scenes("train"):
        scene = components.dataset.load_scene(name)
        frames = scene.train_frames[:: max(1, len(scene.train_frames) // INSTANCE_FRAMES_CHECKED)]
        for index in frames:
            instance = scene.load_frame(index).instance
            count = 0 if instance is None else len(instance.unique())
            if count > slots:
                key = "head.slots" if cfg.get("head") is not None else "model.slots"  # DM-NeRF's slots are its own
                raise ConfigError(
                    f"scene {name!r} frame {index} has {count} instance ids (background included) but "
                    f"{key}={slots}; set {key} >= {count}"
                )


def _scores_owner(cfg: DictConfig) -> str:
    """``head 'unet'``, or ``model '<name>'`` when the model makes its scores without a head (label rendering)."""
    return f"head {cfg.head.name!r}" if cfg.get("head") is not None else f"model {cfg.model.name!r}"
