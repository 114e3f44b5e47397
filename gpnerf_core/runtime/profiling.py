"""Named stages of a training step for torch.profiler, and the step's time attributed to them, backward included.

``stage(name)`` marks the forward work of one stage (the engine marks its own: encoding, projection, transformers,
semantic field, head, loss, optimizer). ``stage_times`` then takes a profiled step's events and charges every
operator to a stage: a forward operator to the innermost stage around it, a backward operator to the stage whose
forward operator made that autograd node (linked by the node's sequence number, as torch's profiler links them),
so "the extractor's convolutions" means their forward *and* their backward. Outside a profiler a stage is a
``record_function`` that records nothing (about a microsecond).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

from torch.autograd.profiler import record_function

STAGE_PREFIX = "gpnerf:"
BACKWARD_EVENT = "autograd::engine::evaluate_function: "
OUTSIDE = "outside the named stages"
GRADIENT_ACCUMULATION = "gradient accumulation"


def stage(name: str) -> record_function:
    """A context manager marking the forward work of stage ``name`` for the profiler."""
    return record_function(STAGE_PREFIX + name)


@dataclass
class StageTime:
    """CPU time of one stage in one profiled step, in seconds (the calling thread's time, intra-op threads inside)."""

    forward: float = 0.0
    backward: float = 0.0

    @property
    def total(self) -> float:
        return self.forward + self.backward


def _owner(event) -> tuple[str | None, object | None]:
    """``("backward", node event)`` inside a backward node, ``("forward", stage event)`` inside a stage, else
    ``(None, None)``; the innermost of them wins."""
    current = event
    while current is not None:
        if current.name.startswith(BACKWARD_EVENT):
            return "backward", current
        if current.name.startswith(STAGE_PREFIX):
            return "forward", current
        current = current.cpu_parent
    return None, None


def stage_times(events: Iterable) -> dict[str, StageTime]:
    """Every event's self CPU time charged to a stage (see the module docstring).

    Args:
        events: ``torch.profiler.profile(...).events()`` of one step.

    Returns:
        Stage name -> ``StageTime``, in the order stages were first met; backward nodes that no stage made
        (parameters' gradient accumulation, work outside any stage) are under ``GRADIENT_ACCUMULATION`` and
        ``OUTSIDE``.
    """
    events = sorted(events, key=lambda event: event.time_range.start)
    # (forward thread, sequence number) -> stage; numbers are per thread. An operator that makes no autograd node
    # records the number the next node will take, so the last operator recording a number is the one that made it.
    owners = [_owner(event) for event in events]
    made_by: dict[tuple[int, int], str] = {}
    for event, (kind, owner) in zip(events, owners):
        if event.sequence_nr >= 0 and kind == "forward":
            made_by[(event.thread, event.sequence_nr)] = owner.name[len(STAGE_PREFIX):]
    times: dict[str, StageTime] = {}
    for event, (kind, owner) in zip(events, owners):
        seconds = event.self_cpu_time_total / 1e6
        if kind == "forward":
            times.setdefault(owner.name[len(STAGE_PREFIX):], StageTime()).forward += seconds
        elif kind == "backward":
            default = GRADIENT_ACCUMULATION if "AccumulateGrad" in owner.name else OUTSIDE
            maker = made_by.get((owner.fwd_thread, owner.sequence_nr), default)
            times.setdefault(maker, StageTime()).backward += seconds
        else:
            times.setdefault(OUTSIDE, StageTime()).forward += seconds
    return times


def stage_table(columns: dict[str, dict[str, StageTime]]) -> str:
    """A text table of stage times: forward, backward and total per stage for each column (a variant), with shares;
    stages in the first column's order, then any the others add."""
    names: list[str] = []
    for times in columns.values():
        names += [name for name in times if name not in names]
    header = f"{'stage':<28}" + "".join(f" | {label + ' fwd / bwd / total s':>36} {'share':>6}" for label in columns)
    lines = [header, "-" * len(header)]
    totals = {label: sum(t.total for t in times.values()) for label, times in columns.items()}
    for name in names:
        cells = ""
        for label, times in columns.items():
            time = times.get(name)
            if time is None:
                cells += f" | {'-':>36} {'':>6}"
            else:
                share = time.total / totals[label] if totals[label] else 0.0
                cells += f" | {time.forward:>10.3f} / {time.backward:>8.3f} / {time.total:>9.3f} {share:>6.1%}"
        lines.append(f"{name:<28}{cells}")
    lines.append(f"{'all':<28}" + "".join(f" | {totals[label]:>36.3f} {'':>6}" for label in columns))
    return "\n".join(lines)
