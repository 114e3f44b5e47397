"""Checks of view selectors: ``select(target_c2w [4, 4], candidate_c2w [N, 4, 4], k, generator) -> positions``."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from gpnerf_core.testing.checks.common import Subject, call, check_build, check_round_trip, expect
from gpnerf_core.testing.inputs import cameras, generator


def select(selector: Any, target: Tensor, candidates: Tensor, k: int, rng: torch.Generator | None = None) -> list:
    """The selection, checked: a list of distinct ints in ``[0, N)``, ``min(k, N)`` of them."""
    what = f"select(target [4, 4], candidates {list(candidates.shape)}, num_views={k}" + (
        ", a generator)" if rng is not None else ", generator=None)")
    chosen = call(what, selector.select, target, candidates, k, rng)
    expect(isinstance(chosen, list), f"{what} returned {type(chosen).__name__}, expected a list of ints")
    expect(all(isinstance(c, int) and not isinstance(c, bool) for c in chosen),
           f"{what} returned {chosen!r}, expected Python ints")
    n = int(candidates.shape[0])
    expect(all(0 <= c < n for c in chosen), f"{what} returned {chosen}, positions outside [0, {n})")
    expect(len(set(chosen)) == len(chosen), f"{what} returned {chosen}, which repeats a view")
    expect(len(chosen) == min(k, n), f"{what} returned {len(chosen)} views {chosen}, expected {min(k, n)}")
    return chosen


def check_selection(subject: Subject) -> None:
    """``k`` distinct valid positions, with and without a generator."""
    selector = subject.build()
    poses = cameras(8)
    for k in (1, 3, 7):
        select(selector, poses[0], poses[1:], k)
        select(selector, poses[0], poses[1:], k, generator(k))


def check_determinism(subject: Subject) -> None:
    """With ``generator=None`` the choice depends on the cameras only (not on torch's global random state)."""
    selector = subject.build()
    poses = cameras(9)
    with torch.random.fork_rng(devices=[]):  # the caller's random state is left as it was
        torch.manual_seed(1)
        first = select(selector, poses[0], poses[1:], 3)
        torch.manual_seed(2)
        second = select(selector, poses[0], poses[1:].clone(), 3)
    expect(first == second, f"select(..., generator=None) returned {first} then {second} for the same cameras")
    seeded = [select(selector, poses[0], poses[1:], 3, generator(7)) for _ in range(2)]
    expect(seeded[0] == seeded[1], f"two generators with the same seed gave {seeded[0]} and {seeded[1]}")


def check_few_candidates(subject: Subject) -> None:
    """Asked for more views than there are candidates, it returns every candidate once."""
    selector = subject.build()
    poses = cameras(4)
    for n in (1, 2):
        for rng in (None, generator(0)):
            chosen = select(selector, poses[0], poses[1 : n + 1], 3, rng)
            expect(sorted(chosen) == list(range(n)), f"{n} candidates, 3 requested: got {chosen}")


def check_degenerate(subject: Subject) -> None:
    """Candidates that all coincide with the target camera still give distinct valid positions."""
    selector = subject.build()
    same = torch.eye(4).repeat(5, 1, 1)
    select(selector, torch.eye(4), same, 3)
    select(selector, torch.eye(4), same, 3, generator(0))


CHECKS = {
    "build": check_build,
    "selection": check_selection,
    "determinism": check_determinism,
    "few candidates": check_few_candidates,
    "degenerate inputs": check_degenerate,
    "config round trip": check_round_trip,
}
