"""What a model family may ask of the training loop: callbacks at fixed points of every step, which see the step, and
how the optimizer treats the family's own learning-rate groups.

A family gives callbacks through ``ModelFamily.training_callbacks`` (nerfstudio's ``get_training_callbacks``): a
schedule tied to the step (pixelSplat's opacity warm-up), or work between the backward pass and the optimizer step (a
per-scene Gaussian family's densification statistics). The trainer runs them on every process, on the model itself
(never its ``DistributedDataParallel`` wrapper), in the order given. ``ModelFamily.optimizer_options`` gives a group's
own learning-rate schedule and Adam epsilon (3D Gaussian splatting decays its positions' rate on its own schedule, with
an epsilon of 1e-15).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Callable

import torch

from gpnerf_core.errors import ConfigError


class TrainingPhase(str, enum.Enum):
    """Where in a training step a callback runs."""

    BEFORE_STEP = "before_step"
    """Before the step's batch is rendered (the forward pass sees what it set)."""
    AFTER_BACKWARD = "after_backward"
    """After the gradients are computed and before gradient clipping and the optimizer step."""
    AFTER_STEP = "after_step"
    """After the optimizer and learning-rate schedule stepped (and the weight average was updated)."""


@dataclass(frozen=True)
class TrainingState:
    """What a callback is told.

    Attributes:
        step: the step being trained, counted from 0 (the optimizer steps done before it; a resumed run continues the
            count).
        total_steps: ``train.steps``.
        optimizer: the optimizer (its ``param_groups`` are named by ``"name"``, the family's group names).
    """

    step: int
    total_steps: int
    optimizer: torch.optim.Optimizer


@dataclass(frozen=True)
class TrainingCallback:
    """Run ``run(state)`` at ``phase`` of every ``every``-th step (steps ``0, every, 2 every, ...``).

    A callback must be deterministic given the step and the model's state: a run resumed from a checkpoint calls it at
    the same steps and must train the same.
    """

    phase: TrainingPhase
    run: Callable[[TrainingState], None]
    every: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.phase, TrainingPhase):
            raise ConfigError(f"training callback phase {self.phase!r}: expected a TrainingPhase member")
        if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 1:
            raise ConfigError(f"training callback every={self.every!r}: expected an integer >= 1")
        if not callable(self.run):
            raise ConfigError(f"training callback run={self.run!r}: expected a callable taking a TrainingState")

    def due(self, step: int) -> bool:
        return step % self.every == 0


@dataclass(frozen=True)
class GroupOptions:
    """How the optimizer treats one learning-rate group of a family, where it differs from the run's.

    Attributes:
        lr_factor: ``step -> factor`` of the group's rate (step 0 is the first optimizer step), in place of
            ``train.lr_schedule``'s (with its warm-up); None keeps the run's schedule.
        eps: Adam's epsilon for the group (None: torch's 1e-8).
    """

    lr_factor: Callable[[int], float] | None = None
    eps: float | None = None

    def __post_init__(self) -> None:
        if self.lr_factor is not None and not callable(self.lr_factor):
            raise ConfigError(f"GroupOptions lr_factor={self.lr_factor!r}: expected a callable step -> factor")
        if self.eps is not None and (isinstance(self.eps, bool) or not isinstance(self.eps, (int, float))
                                     or not 0 < self.eps < 1):
            raise ConfigError(f"GroupOptions eps={self.eps!r}: expected a number in (0, 1)")
