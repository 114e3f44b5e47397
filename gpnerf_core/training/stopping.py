"""Stop rules of a fit: a target on a held-out metric, a plateau of it, a training-seconds budget.

``Stopper`` is told each evaluation's value (``observe``) and the training seconds after each step (``spent``) and says
whether and why to stop (a ``StopDecision``). ``stopping_callback`` runs it inside ``Trainer.fit`` as an untimed
``TrainingCallback`` that evaluates at chosen steps and asks the loop to stop (``TrainingState.request_stop``): the loop
then ends after that step, writes its checkpoint there and returns normally.

Deterministic: the target and the plateau read evaluations at fixed steps, and evaluation draws no random numbers, so
with the same seed and config they stop at the same step. The seconds budget reads the wall clock (training time,
evaluations excluded): where it stops depends on the machine and its load, and is not reproducible step for step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

from gpnerf_core.errors import ConfigError
from gpnerf_core.interfaces.training import TrainingCallback, TrainingPhase, TrainingState

LOWER_IS_BETTER = ("depth/", "lpips/")
"""Prefixes of the metric names whose smaller values are better (errors, distances); every other is higher-better."""
REASONS = ("steps", "seconds", "target", "plateau")
"""Why a fit stops: ``train.steps`` reached, the seconds budget spent, the target reached, a plateau."""


def lower_is_better(metric: str) -> bool:
    """Whether smaller values of ``metric`` are better (``depth/abs_rel``, ``lpips/vgg``)."""
    return metric.startswith(LOWER_IS_BETTER)


@dataclass(frozen=True)
class StopRules:
    """What ends a fit besides its step budget.

    Attributes:
        metric: the held-out metric the target and the plateau read (its name, for the messages).
        target: stop once ``metric`` reaches it (None: no target).
        patience: stop after this many evaluations in a row without a gain of ``min_delta`` over the best (0: none).
        min_delta: the smallest gain that counts, in the metric's units (>= 0).
        seconds: training-seconds budget (0: none); not deterministic (the module docstring).
        lower_better: smaller values of ``metric`` are better (default: from its name, ``lower_is_better``).
    """

    metric: str = "miou/image_mean_present"
    target: float | None = None
    patience: int = 0
    min_delta: float = 0.005
    seconds: float = 0.0
    lower_better: bool | None = None

    def __post_init__(self) -> None:
        if self.target is not None and not math.isfinite(self.target):
            raise ConfigError(f"fit.target={self.target}: expected null or a finite value of fit.metric")
        if self.patience < 0:
            raise ConfigError(f"fit.patience={self.patience}: expected an integer >= 0 (0 = no plateau rule)")
        if not (math.isfinite(self.min_delta) and self.min_delta >= 0):
            raise ConfigError(f"fit.min_delta={self.min_delta}: expected a finite gain >= 0")
        if not (math.isfinite(self.seconds) and self.seconds >= 0):
            raise ConfigError(f"fit.seconds={self.seconds}: expected a finite training-seconds budget >= 0 (0 = none)")
        if self.lower_better is None:
            object.__setattr__(self, "lower_better", lower_is_better(self.metric))

    @property
    def reads_metric(self) -> bool:
        """A rule reads the held-out metric (a target or a plateau): the fit must evaluate while it trains."""
        return self.target is not None or self.patience > 0


@dataclass(frozen=True)
class StopDecision:
    """Why a fit stops.

    Attributes:
        reason: one of ``REASONS``.
        step: the step it stops at (optimizer steps done).
        said: the reason in words, one line (``plateau (no gain of 0.005 in 3 evaluations; best 0.912 at step 800)``).
    """

    reason: str
    step: int
    said: str


@dataclass
class Stopper:
    """Applies ``rules`` to a fit's evaluations (``observe``) and training seconds (``spent``).

    Attributes:
        best, best_step: the best value of the metric so far and the step it was reached at (None before any).
        without_gain: evaluations since the last gain of at least ``min_delta`` over the best.
        decision: the first stop it said (None: go on); it says no other after it.
    """

    rules: StopRules
    best: float | None = None
    best_step: int | None = None
    without_gain: int = 0
    decision: StopDecision | None = field(default=None)

    def observe(self, step: int, value: float | None) -> StopDecision | None:
        """The held-out metric ``value`` at ``step`` (optimizer steps done; 0 = the start): a stop by the target
        (checked first) or the plateau, else None. A gain is a value better than the best by more than 0 and at least
        ``min_delta`` (Keras's ``EarlyStopping``: the best moves only on a gain); a None value (not scored) is none."""
        if self.decision is not None:
            return self.decision
        rules = self.rules
        metric = rules.metric
        sign = -1.0 if rules.lower_better else 1.0
        if value is not None and math.isfinite(value):
            if rules.target is not None and sign * value >= sign * rules.target:
                return self._stop("target", step, f"target ({metric} {value:.3f} {'<=' if sign < 0 else '>='} "
                                                  f"{rules.target:g} at step {step})")
            gain = math.inf if self.best is None else sign * (value - self.best)
            if gain > 0 and gain >= rules.min_delta:
                self.best, self.best_step, self.without_gain = value, step, 0
                return None
        self.without_gain += 1
        if rules.patience and self.without_gain >= rules.patience:
            best = "none" if self.best is None else f"{self.best:.3f} at step {self.best_step}"
            return self._stop("plateau", step, f"plateau (no gain of {rules.min_delta:g} in {self.without_gain} "
                                               f"evaluation{'s' if self.without_gain != 1 else ''}; best {best})")
        return None

    def spent(self, step: int, seconds: float) -> StopDecision | None:
        """The training ``seconds`` after ``step``: a stop once they reach the budget, else None."""
        if self.decision is not None:
            return self.decision
        budget = self.rules.seconds
        if budget > 0 and seconds >= budget:
            return self._stop("seconds", step, f"seconds (budget of {budget:g} s spent: {seconds:.2f} s of training)")
        return None

    def _stop(self, reason: str, step: int, said: str) -> StopDecision:
        self.decision = StopDecision(reason, step, said)
        return self.decision


def stopping_callback(stopper: Stopper, steps: Sequence[int], evaluate: Callable[[int], float | None]
                      ) -> TrainingCallback:
    """An untimed ``TrainingCallback``: after each of ``steps`` (optimizer steps done) ``evaluate(step)`` gives the
    held-out metric, which ``stopper`` observes; after every step it is told the training seconds
    (``TrainingState.seconds``). A stop is asked of the loop (``TrainingState.request_stop``), which ends after
    this step.

    Args:
        steps: where to evaluate (the curve's points below ``train.steps``).
        evaluate: evaluates the model now, records the point and returns the value of the rules' metric.
    """
    wanted = frozenset(int(step) for step in steps)

    def run(state: TrainingState) -> None:
        done = state.steps_done
        decision = stopper.observe(done, evaluate(done)) if done in wanted else None
        decision = decision or stopper.spent(done, state.seconds)
        if decision is not None:
            if state.request_stop is None:
                raise RuntimeError("stopping_callback: the training loop offers no request_stop")
            state.request_stop(decision.said)

    return TrainingCallback(TrainingPhase.AFTER_STEP, run, timed=False)
