"""Where ``fit``'s per-scene Gaussian family starts: the scene's points (the family's own ``hooks.initialise``, as
``run`` starts it), or a generalizable model's prediction of the scene (``checkpoint=<run's .pt>``).

``starting_point`` is the one function a checkpoint start plugs into; the command applies what it returns
(``apply_start``) before the family is built and the trainer initialises its Gaussians.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

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

    Called after the process is set up (threads, seed, device: ``dist.device``) and before the per-scene family is
    built. Returns a ``FitStart`` with ``kind="checkpoint"``, ``checkpoint=str(checkpoint)``, the wall ``seconds`` the
    prediction took, its ``notes``, the config ``overrides`` the start needs (``start_overrides``) and the ``start``
    the family takes (``family.start = start``; a ``GaussianStart``); options: ``fit.start_every``,
    ``fit.start_opacity``.
    """
    raise NotImplementedError(f"fit checkpoint={checkpoint}: the start from a generalizable model "
                              "(gpnerf_core.model.generalized_start) is not wired in yet")


def apply_start(cfg: DictConfig, start: FitStart, given: list[str]) -> DictConfig:
    """``cfg`` itself where the start needs no overrides; else the config composed again from the command's overrides
    (``given``: the job's, ``runs.task_overrides``) and the start's after them (group choices such as ``+head=<name>``
    included; a key both set takes the start's value), validated."""
    if not start.overrides:
        return cfg
    from gpnerf_core.config.overrides import override_key
    from gpnerf_core.engine.setup import compose_checked

    from hydra.core.global_hydra import GlobalHydra

    keys = {override_key(o) for o in start.overrides}
    job = GlobalHydra.instance()
    running = job.hydra if job.is_initialized() else None
    job.clear()  # inside a Hydra job: compose beside it, then give the job its Hydra back
    try:
        return compose_checked([*(o for o in given if override_key(o) not in keys), *start.overrides])
    finally:
        if running is not None:
            GlobalHydra.instance().clear()
            GlobalHydra.instance().initialize(running)


def give_start(family: Any, start: FitStart) -> None:
    """Hand a checkpoint start to the built family (``family.start``), before the trainer initialises it."""
    if start.start is not None:
        family.start = start.start
