"""The one callback protocol of the training loop, and how the optimizer treats a family's learning-rate groups.

``Trainer.fit(callbacks=...)`` and a model family's hooks (``FamilyHooks.callbacks``, nerfstudio's
``get_training_callbacks``) give the same thing: ``TrainingCallback`` s that run at a fixed point of a step and are
told the step (``TrainingState``), including what the step's forward pass returned (``outputs``: a rasterizer's
projected centres and footprints reach a densification callback as an argument, gsplat's ``info``). A family's
callbacks do its own work on the step's clock (a schedule tied to the step, densification statistics); a command's
(``training.callbacks.evaluate_at``) run off the clock (``timed=False``: an evaluation). The trainer runs them on every
process, on the model itself (never its ``DistributedDataParallel`` wrapper), in the order given.
``FamilyHooks.optimizer_options`` gives a group's own learning-rate schedule and Adam epsilon (``GroupOptions``: 3D
Gaussian splatting decays its positions' rate on its own schedule, with an epsilon of 1e-15).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from gpnerf_core.errors import ConfigError
from gpnerf_core.types import StepBatch, StepOutput


class TrainingPhase(str, enum.Enum):
    """Where in a training step a callback runs."""

    BEFORE_STEP = "before_step"
    """Before the step's batch is rendered (the forward pass sees what it set)."""
    BEFORE_BACKWARD = "before_backward"
    """After the forward pass and the loss, before ``backward`` (gsplat's ``step_pre_backward``: keep the gradient of
    an intermediate tensor of the step's outputs)."""
    AFTER_BACKWARD = "after_backward"
    """After the gradients are computed and before gradient clipping and the optimizer step."""
    AFTER_STEP = "after_step"
    """After the optimizer and learning-rate schedule stepped (and the weight average was updated)."""


@dataclass(frozen=True)
class TrainingState:
    """What a callback (and a family's loss terms) is told.

    Attributes:
        step: the step being trained, counted from 0 (the optimizer steps done before it; a resumed run continues the
            count). After the step, ``steps_done`` is ``step + 1``.
        total_steps: ``train.steps``.
        optimizer: the optimizer (its ``param_groups`` are named by ``"name"``, the family's group names).
        batch: the step's target views (None before they are drawn: ``BEFORE_STEP``).
        outputs: what the step's forward pass returned (``StepOutput``: one ``ViewOutput`` or ``ImageOutput`` per target
            view, with the family's ``extras``; after ``backward`` their tensors hold the gradients retained at
            ``BEFORE_BACKWARD``), or None before the forward pass (``BEFORE_STEP``).
        seconds: training seconds so far (earlier runs of a resumed run included; off-the-clock callbacks excluded).
        checkpoint: writes a checkpoint at this point and returns its path (rank 0; every process must call it), for a
            command's callback whose work must survive an interruption; None where the loop offers none.
        request_stop: ``request_stop(reason)`` ends ``Trainer.fit`` cleanly after this step (its checkpoint written at
            this step, ``TrainResult.stopped`` = ``reason``, one line): a command's stop rule
            (``training.stopping``); None where the loop offers none.
    """

    step: int
    total_steps: int
    optimizer: torch.optim.Optimizer
    batch: StepBatch | None = None
    outputs: StepOutput | None = None
    seconds: float = 0.0
    checkpoint: Callable[[], Path | None] | None = None
    request_stop: Callable[[str], None] | None = None

    @property
    def steps_done(self) -> int:
        """Optimizer steps done once this step has stepped."""
        return self.step + 1


@dataclass(frozen=True)
class TrainingCallback:
    """Run ``run(state)`` at ``phase`` of every ``every``-th step (steps ``0, every, 2 every, ...``).

    A callback must be deterministic given the step and the model's state: a run resumed from a checkpoint calls it at
    the same steps and must train the same.

    Attributes:
        timed: its time is training time (a family's own work: statistics, densification, a schedule). False: a
            command's work that runs off the training clock, once the step is done and checkpointed (``AFTER_STEP``
            only): a stop signal may cut it short in a single process, and the model is back in training mode after
            it (an evaluation).
    """

    phase: TrainingPhase
    run: Callable[[TrainingState], None]
    every: int = 1
    timed: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.phase, TrainingPhase):
            raise ConfigError(f"training callback phase {self.phase!r}: expected a TrainingPhase member")
        if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 1:
            raise ConfigError(f"training callback every={self.every!r}: expected an integer >= 1")
        if not callable(self.run):
            raise ConfigError(f"training callback run={self.run!r}: expected a callable taking a TrainingState")
        if not self.timed and self.phase is not TrainingPhase.AFTER_STEP:
            raise ConfigError(f"training callback timed=False at {self.phase.value}: a callback off the training "
                              "clock runs after the step (TrainingPhase.AFTER_STEP)")

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
