"""Where ``fit``'s per-scene Gaussian family starts: the scene's points (the family's own ``hooks.initialise``, as
``run`` starts it), or a generalizable model's prediction of the scene (``checkpoint=<run's .pt>``).

``starting_point`` is the one function a checkpoint start plugs into; the command applies what it returns
(``apply_start``) before the family is built and the trainer initialises its Gaussians.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from omegaconf import DictConfig, OmegaConf

from gpnerf_core.errors import ConfigError
from gpnerf_core.runtime.distributed import Distributed

START_KINDS = ("points", "checkpoint")


@dataclass(frozen=True)
class FitStart:
    """How the fit's Gaussians start.

    Attributes:
        kind: ``points`` (the scene's points or depth, the family's own start) or ``checkpoint`` (a generalizable
            model's prediction).
        checkpoint: the generalizable run's ``.pt`` (None for ``points``).
        seconds: wall seconds the start took before training (a checkpoint's prediction; 0 for ``points``): the
            curve's ``seconds`` are these plus the training seconds.
        notes: lines to print once (classes that differ, a budget below the start's count, ...).
        overrides: Hydra overrides the start needs (``start_overrides``: ``model.feature_dim=C``, ``+head=<name>``,
            ...), composed after the command's before the family is built (``apply_start``).
        start: what the family takes as ``family.start`` before the trainer initialises its Gaussians (None: the
            family's own start from the scene's points).
    """

    kind: str = "points"
    checkpoint: str | None = None
    seconds: float = 0.0
    notes: tuple[str, ...] = ()
    overrides: tuple[str, ...] = ()
    start: Any = None

    def __post_init__(self) -> None:
        if self.kind not in START_KINDS:
            raise ValueError(f"FitStart kind={self.kind!r}: expected one of {', '.join(START_KINDS)}")


def checkpoint_of(cfg: DictConfig) -> Path | None:
    """``checkpoint=`` of the fit: the generalizable run's checkpoint file (None: not given); a path that is not a
    file is refused naming it."""
    given = cfg.get("checkpoint")
    if not given:
        return None
    path = Path(str(given))
    if not path.is_file():
        raise ConfigError(f"checkpoint={given}: no such file; expected a generalizable run's checkpoint (a .pt file "
                          "in its checkpoints/ folder), or no checkpoint= to start from the scene's points")
    return path


def starting_point(cfg: DictConfig, checkpoint: Path, dist: Distributed) -> FitStart:
    """The start a generalizable model's checkpoint predicts for the fit's one scene (``dataset.scenes``).

    The checkpoint is opened on the fit's data (its own config with the fit's ``dataset``, ``view_selector`` and
    process keys: ``open_trained``), its model predicts the scene's Gaussians (``generalized_start.predict_start``:
    every ``fit.start_every``-th training frame, ray families' cells at ``fit.start_opacity``, at most
    ``model.max_gaussians``), and the per-scene family's config is sized to carry them (``start_overrides``). Called
    after the process is set up and before the family is built; ``seconds`` is the wall time of opening and
    predicting (the curve's ``seconds`` add it to the training seconds).

    Raises:
        ConfigError: the checkpoint's family is per-scene, or predicts no Gaussians and renders no depth
            (``predict_start`` names it).
    """
    import time

    from gpnerf_core.config.overrides import override_key
    from gpnerf_core.data.frames import FrameCache
    from gpnerf_core.engine.opening import open_trained
    from gpnerf_core.engine.runs import task_overrides
    from gpnerf_core.model.generalized_start import predict_start, start_overrides
    from gpnerf_core.model.trained import load_trained

    started = time.perf_counter()
    trained = load_trained(checkpoint)
    data = [o for o in task_overrides() if override_key(o).split(".")[0] in OPENED_KEYS]
    with beside_the_job():
        opened = open_trained(trained, data, command="fit", device=dist.device, other_data=True,
                              source="fit checkpoint={path}")
    model = opened.components.model.eval()
    frames = FrameCache(opened.components.dataset, dist.device)
    scene = frames.scene(opened.components.dataset.scenes("train")[0])
    head = opened.cfg.get("head")
    common = dict(num_source_views=int(opened.cfg.model.num_source_views), every=int(cfg.fit.start_every),
                  tolerance=float(cfg.fit.start_tolerance), chunk_rays=int(cfg.eval.chunk_rays), family=trained.family,
                  classes=tuple(opened.components.classes.names),
                  head_config=OmegaConf.to_container(head, resolve=True) if head is not None else None)
    typed = {override_key(o) for o in task_overrides()}
    if str(cfg.fit.start_geometry) == "points":
        start, origin = start_at_points(cfg, model, frames, opened.components.view_selector, scene, common)
        notes = (*opened.notes, f"the start: {start.gaussians.count} Gaussians at the scene's {origin} with the "
                 f"semantics model {trained.family!r} predicts for them in {len(start.frames)} training frames "
                 f"(semantics: {start.semantics})")
        schedule = []  # a start from points keeps the family's own schedule (its opacity resets clear their floaters)
    else:
        start = predict_start(
            model, frames, opened.components.view_selector, scene, **common,
            budget=int(cfg.fit.start_budget) or int(cfg.model.max_gaussians), opacity=float(cfg.fit.start_opacity),
            min_views=int(cfg.fit.start_min_views), max_conflicts=int(cfg.fit.start_conflicts),
            budget_key="fit.start_budget" if int(cfg.fit.start_budget) else "model.max_gaussians")
        if not bool(cfg.fit.start_semantics):
            start = without_semantics(start)
        notes = (*opened.notes, f"the start: {start.gaussians.count} Gaussians of model {trained.family!r} from "
                 f"{len(start.frames)} training frames ({start.predicted} predicted before merging where views "
                 f"overlap; semantics: {start.semantics})")  # the start's own notes: said once when the family begins
        schedule = [] if "model.opacity_reset_every" in typed else [f"model.opacity_reset_every={KEEP_OPACITIES}"]
    targets: list[str] = []
    if opened.components.classes.from_checkpoint and "labels_from" in cfg.dataset and not cfg.dataset.labels_from:
        folder = predicted_labels(checkpoint, opened, model, frames, scene)
        targets = [f"dataset.labels_from={folder}"]
        notes = (*notes, f"scene {scene.name!r} has no labels: model {trained.family!r}'s labels of its "
                 f"{scene.num_frames} frames are the fit's targets and the start's classes ({folder})")
    return FitStart(kind="checkpoint", checkpoint=str(checkpoint), seconds=time.perf_counter() - started,
                    notes=notes, overrides=(*start_overrides(start), *schedule, *targets), start=start)


def start_at_points(cfg: DictConfig, model: Any, frames: Any, selector: Any, scene: Any, common: dict
                    ) -> tuple[Any, str]:
    """``fit.start_geometry=points``: the scene's own points as the fit's family would start from them
    (``starting_points`` with its ``model.init_points`` and ``model.init_depth_stride``, opacity ``model.init_opacity``;
    drawn on a forked random stream, so the fit's own stream is as without a start) with the model's semantics
    (``points_start``), and where the points came from (``sparse points`` or ``depth``)."""
    import torch

    from gpnerf_core.geometry.gaussians.initialisation import starting_points
    from gpnerf_core.model.generalized_start import points_start

    if not bool(cfg.fit.start_semantics):
        raise ConfigError("fit.start_geometry=points with fit.start_semantics=false takes nothing from the checkpoint "
                          "(the scene's points, the model's semantics); expected fit.start_semantics=true, or no "
                          "checkpoint= to start from the scene's points alone")
    with torch.random.fork_rng(devices=[]):
        points, origin = starting_points(scene, int(cfg.model.init_points), int(cfg.model.init_depth_stride))
    return points_start(model, frames, selector, scene, points, opacity=float(cfg.model.init_opacity), origin=origin,
                        **common), origin


def without_semantics(start: Any) -> Any:
    """``start`` with its geometry and colour only (``fit.start_semantics=false``): no features, no head."""
    import dataclasses

    return dataclasses.replace(start, gaussians=dataclasses.replace(start.gaussians, features=None),
                               semantics="none", head_state=None, head_config=None, feature_levels=1,
                               feature_stride=1)


def predicted_labels(checkpoint: Path, opened: Any, model: Any, frames: Any, scene: Any) -> Path:
    """The generalizable model's labels of every frame of ``scene`` (``label``'s files, which a capture's
    ``dataset.labels_from`` reads), in ``$GPNERF_CACHE/labels/<key>`` (default ``~/.cache/gpnerf``), keyed by the
    checkpoint file (path, size, modification time), the data and the image size: written once, all or none, and
    read again by the next fit of that scene from that checkpoint (the three seeds of one capture, say)."""
    import hashlib
    import os
    import time
    from functools import partial

    import numpy as np

    from gpnerf_core.evaluation.evaluator import component_names
    from gpnerf_core.model.predicted_labels import LABELS_FILE, frame_label_writes, labels_record
    from gpnerf_core.runtime.io import atomic_write_json
    from gpnerf_core.runtime.staging import write_staged

    stat = checkpoint.resolve().stat()
    data = OmegaConf.to_container(opened.cfg.dataset, resolve=True)
    key = hashlib.sha256(repr((str(checkpoint.resolve()), stat.st_size, stat.st_mtime_ns, data, scene.name,
                               scene.height, scene.width)).encode()).hexdigest()[:16]
    base = Path(os.environ.get("GPNERF_CACHE") or Path.home() / ".cache" / "gpnerf").expanduser() / "labels"
    folder = base / f"{scene.name}-{key}"
    if (folder / LABELS_FILE).is_file():
        return folder
    if (folder / "labels").is_dir():  # an interrupted write of this cache entry: written again
        import shutil

        shutil.rmtree(folder / "labels")
    folder.mkdir(parents=True, exist_ok=True)
    classes = opened.components.classes
    started = time.perf_counter()
    writes = frame_label_writes(model, frames, opened.components.view_selector, scene,
                                int(opened.cfg.model.num_source_views), int(opened.cfg.eval.chunk_rays),
                                model.hooks.output_owners(component_names(opened.cfg)),
                                np.uint8 if classes.num_classes <= 255 else np.uint16)
    record = labels_record(scene, classes, int(opened.components.dataset.ignore_index), str(checkpoint),
                           str(opened.cfg.model.name), int(opened.cfg.model.num_source_views),
                           time.perf_counter() - started)
    write_staged(folder, [*writes, (LABELS_FILE, partial(atomic_write_json, obj=record))], ".labels.partial-")
    return folder


KEEP_OPACITIES = 10**9
"""``model.opacity_reset_every`` of a started fit unless the command sets it: no opacity reset. 3DGS caps every
opacity at 0.01 every 3000 of its 30k steps to clear floaters grown from a sparse start; a started fit begins from
Gaussians whose opacities are the generalizable model's answer (AnySplat's post-optimisation turns density control off,
InstantSplat densifies nothing), and a reset would throw that answer away at the first one (every 200 steps of a
2000-step fit). Densification within ``model.max_gaussians`` and opacity pruning stay."""


OPENED_KEYS = ("dataset", "view_selector", "device", "threads", "seed")
"""The fit's overrides that the generalizable checkpoint is opened with (its own config otherwise): the data it
predicts and the process it runs in."""


def apply_start(cfg: DictConfig, start: FitStart, given: list[str]) -> DictConfig:
    """``cfg`` itself where the start needs no overrides; else the config composed again from the command's overrides
    (``given``: the job's, ``runs.task_overrides``) and the start's after them (group choices such as ``+head=<name>``
    included; a key both set takes the start's value), validated."""
    if not start.overrides:
        return cfg
    from gpnerf_core.config.overrides import override_key
    from gpnerf_core.engine.setup import compose_checked

    keys = {override_key(o) for o in start.overrides}
    with beside_the_job():
        return compose_checked([*(o for o in given if override_key(o) not in keys), *start.overrides])


@contextmanager
def beside_the_job() -> Iterator[None]:
    """Compose configs inside a Hydra job (the checkpoint's, the start's): Hydra's global state is cleared for the
    block and the job's given back after it."""
    from hydra.core.global_hydra import GlobalHydra

    job = GlobalHydra.instance()
    running = job.hydra if job.is_initialized() else None
    job.clear()
    try:
        yield
    finally:
        if running is not None:
            GlobalHydra.instance().clear()
            GlobalHydra.instance().initialize(running)


def give_start(family: Any, start: FitStart, scene_classes: tuple[str, ...] | None) -> None:
    """Hand a checkpoint start to the built family (``GaussianFamily.use_start``), before the trainer initialises it;
    ``scene_classes``: the fit's dataset's class names (a start of other classes keeps only its geometry and colour)."""
    if start.start is not None:
        family.use_start(start.start, scene_classes)
