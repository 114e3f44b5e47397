"""What a command runs inside ``Trainer.fit`` besides training: the curve points it evaluates at.

``evaluate_at`` makes a ``TrainingCallback`` (the one protocol of the training loop, the same a model family's hooks
give) with ``timed=False``: ``fit`` runs it after a step and that step's own checkpoint, does not count its time as
training time, and puts the model back in training mode after it. Evaluation draws no random numbers, so training with
curve points trains exactly as without.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

from gpnerf_core.interfaces.training import TrainingCallback, TrainingPhase, TrainingState


def evaluate_at(steps: Sequence[int], evaluate: Callable[[], Any], entries: list[Any] | None = None
                 ) -> TrainingCallback:
    """After each of ``steps`` (optimizer steps done), a checkpoint (a resumed run keeps the point) then
    ``evaluate()``; the entries it returns are appended to ``entries`` when given.

    Args:
        steps: training steps to evaluate at.
        evaluate: makes the curve entry (any record the command keeps), reading the trainer it closes over.
    """
    wanted = frozenset(int(step) for step in steps)

    def run(state: TrainingState) -> None:
        if state.steps_done in wanted:
            if state.checkpoint is not None:
                state.checkpoint()
            entry = evaluate()
            if entries is not None:
                entries.append(entry)

    return TrainingCallback(TrainingPhase.AFTER_STEP, run, timed=False)
