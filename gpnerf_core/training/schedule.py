"""Learning-rate schedules: a factor of each group's base rate per optimizer step."""

from __future__ import annotations

import math
from typing import Callable

from gpnerf_core.errors import ConfigError

LR_SCHEDULES = ("exponential", "cosine")


def lr_factor(
    schedule: str, *, steps: int, warmup_steps: int, decay_rate: float, decay_steps: int
) -> Callable[[int], float]:
    """``step -> factor`` for ``torch.optim.lr_scheduler.LambdaLR`` (step 0 is the first optimizer step).

    Warm-up: ``(step + 1) / warmup_steps`` for the first ``warmup_steps`` steps. Then ``exponential``:
    ``decay_rate ** (step / decay_steps)``, or ``cosine``: ``0.5 * (1 + cos(pi * t))`` with ``t`` going from 0 at the
    end of the warm-up to 1 at ``steps``.
    """
    if schedule not in LR_SCHEDULES:
        raise ConfigError(f"train.lr_schedule={schedule!r}: expected one of {', '.join(LR_SCHEDULES)}")
    if decay_steps <= 0 or not 0 < decay_rate <= 1:
        raise ConfigError(
            f"train.lr_decay_rate must be in (0, 1] and lr_decay_steps > 0, got {decay_rate} and {decay_steps}"
        )
    if warmup_steps < 0:
        raise ConfigError(f"train.warmup_steps={warmup_steps}: expected an integer >= 0")

    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        if schedule == "exponential":
            return decay_rate ** (step / decay_steps)
        t = min(1.0, (step - warmup_steps) / max(1, steps - warmup_steps))
        return 0.5 * (1.0 + math.cos(math.pi * t))

    return factor
