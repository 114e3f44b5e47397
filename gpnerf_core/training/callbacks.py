"""What runs inside ``Trainer.fit`` after each step besides training: the curve points a command evaluates at.

A callback (``trainer.Callback``) has ``after_step(trainer)``; ``fit`` calls it after every step (and after the step's own checkpoint), does
not count its time as training time, and puts the model back in training mode after it. Evaluation draws no random
numbers, so training with callbacks trains exactly as without.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from gpnerf_core.training.trainer import Trainer


@dataclass
class CurvePoints:
    """At each of ``steps``, a checkpoint (a resumed run keeps the point) then ``evaluate(trainer)``; the entries it
    returns are collected in ``entries``.

    Attributes:
        steps: training steps to evaluate at.
        evaluate: ``trainer -> curve entry`` (any record the command keeps).
    """

    steps: Sequence[int]
    evaluate: Callable[[Trainer], Any]
    entries: list[Any] = field(default_factory=list)

    def after_step(self, trainer: Trainer) -> None:
        if trainer.step in self.steps:
            trainer.checkpoint()
            self.entries.append(self.evaluate(trainer))
