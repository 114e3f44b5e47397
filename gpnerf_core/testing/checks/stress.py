"""Checks of stress cases (``gpnerf_register_stress_cases``): levels, source choice, target choice, perturbation,
determinism.

A case is checked on a synthetic scene of 24 frames on a circle (every 4th held out) and on random source views
``[V, 3, 20, 24]``, at every level the case says it can run there.
"""

from __future__ import annotations

from typing import Any, Callable

import torch

from gpnerf_core.interfaces import StressCase
from gpnerf_core.registry.components import stress_case_problem
from gpnerf_core.testing.checks.common import call, expect
from gpnerf_core.testing.inputs import cameras, generator
from gpnerf_core.types import Scene, SourceViews
from gpnerf_core.runtime.finite import all_finite

FRAMES, HELD_OUT_EVERY, VIEWS, HEIGHT, WIDTH = 24, 4, 4, 20, 24


def scene() -> Scene:
    """A synthetic scene: ``FRAMES`` cameras on a circle, every ``HELD_OUT_EVERY``-th frame held out."""
    poses = cameras(FRAMES)
    intrinsics = torch.tensor([[20.0, 0.0, WIDTH / 2], [0.0, 20.0, HEIGHT / 2], [0.0, 0.0, 1.0]]).repeat(FRAMES, 1, 1)
    held_out = tuple(range(HELD_OUT_EVERY // 2, FRAMES, HELD_OUT_EVERY))

    def no_frames(index: int) -> Any:
        raise AssertionError("a stress case reads cameras and frame lists, not frames")

    return Scene("kit_scene", poses, intrinsics, HEIGHT, WIDTH, 0.1, 5.0,
                 tuple(i for i in range(FRAMES) if i not in held_out), held_out, no_frames)


def sources(count: int = VIEWS) -> SourceViews:
    poses = cameras(count, seed=1)
    intrinsics = torch.tensor([[20.0, 0.0, WIDTH / 2], [0.0, 20.0, HEIGHT / 2], [0.0, 0.0, 1.0]]).repeat(count, 1, 1)
    return SourceViews(torch.rand(count, 3, HEIGHT, WIDTH, generator=generator(2)), intrinsics, poses)


def runnable_levels(case: StressCase) -> list[float]:
    """The levels the case says it can evaluate on the synthetic scene with ``VIEWS`` source views."""
    return [level for level in case.levels
            if call(f"unavailable(level={level})", case.unavailable, level, {}, [scene()], VIEWS) is None]


def check_levels(case: StressCase) -> None:
    """Registration rules, plus a string label per level and a string or None from ``unavailable``."""
    problem = stress_case_problem(case)
    expect(problem is None, f"{problem}")
    for level in case.levels:
        label = call(f"label({level})", case.label, level)
        expect(isinstance(label, str) and label, f"label({level}) is {label!r}, expected a non-empty string")
        reason = call(f"unavailable(level={level})", case.unavailable, level, {}, [scene()], VIEWS)
        expect(reason is None or isinstance(reason, str), f"unavailable(level={level}) returned {reason!r}, "
                                                          "expected None or a reason")
        overrides = call(f"dataset_overrides(level={level})", case.dataset_overrides, level, {})
        expect(isinstance(overrides, dict) and all(isinstance(k, str) for k in overrides),
               f"dataset_overrides(level={level}) returned {overrides!r}, expected {{dataset key: value}}")


def check_sources(case: StressCase) -> None:
    """``num_source_views`` a positive int; ``source_indices`` that many distinct training frames, never the target."""
    the_scene = scene()

    def nearest(scene_: Scene, target: int, count: int) -> list[int]:
        candidates = [i for i in scene_.train_frames if i != target]
        distance = (scene_.c2w[candidates, :3, 3] - scene_.c2w[target, :3, 3]).norm(dim=-1)
        return [candidates[i] for i in torch.argsort(distance)[:count].tolist()]

    for level in runnable_levels(case):
        count = call(f"num_source_views(level={level}, trained={VIEWS})", case.num_source_views, level, VIEWS)
        expect(isinstance(count, int) and count >= 1,
               f"num_source_views(level={level}) returned {count!r}, expected an int >= 1")
        for target in the_scene.eval_frames:
            what = f"source_indices(level={level}, target={target}, num_views={count})"
            chosen = call(what, case.source_indices, level, the_scene, target, count, nearest)
            expect(isinstance(chosen, list) and all(isinstance(i, int) for i in chosen),
                   f"{what} returned {chosen!r}, expected a list of frame indices")
            expect(len(chosen) == count and len(set(chosen)) == count,
                   f"{what} returned {chosen}, expected {count} distinct frames")
            expect(target not in chosen and set(chosen) <= set(the_scene.train_frames),
                   f"{what} returned {chosen}: sources must be training frames, never the target")


def check_targets(case: StressCase) -> None:
    """``target_frames`` a non-empty list of distinct held-out frames of the scene (never a training frame)."""
    the_scene = scene()
    held_out = list(the_scene.eval_frames)
    for level in runnable_levels(case):
        what = f"target_frames(level={level}, eval_frames={held_out})"
        chosen = call(what, case.target_frames, level, the_scene, held_out)
        expect(isinstance(chosen, list) and all(isinstance(i, int) for i in chosen),
               f"{what} returned {chosen!r}, expected a list of frame indices")
        expect(bool(chosen) and len(set(chosen)) == len(chosen) and set(chosen) <= set(held_out),
               f"{what} returned {chosen}: expected distinct held-out frames, at least one (a training frame would be "
               "scored against the data the model was fitted on)")


def _perturbed(
    case: StressCase, level: float, seed: int, in_place_fails: bool = True
) -> tuple[SourceViews, SourceViews]:
    given = sources()
    kept = SourceViews(given.rgb.clone(), given.intrinsics.clone(), given.c2w.clone())
    out = call(f"perturb_sources(level={level}, sources [{VIEWS}, 3, {HEIGHT}, {WIDTH}])", case.perturb_sources,
               level, given, torch.Generator().manual_seed(seed))
    expect(not in_place_fails or (torch.equal(given.rgb, kept.rgb) and torch.equal(given.c2w, kept.c2w)),
           f"perturb_sources(level={level}) changed its input in place; return new tensors")
    return kept, out


def check_perturbation(case: StressCase) -> None:
    """Same shapes and dtypes, finite, images in [0, 1], rigid camera-to-world poses."""
    for level in runnable_levels(case):
        given, out = _perturbed(case, level, 0)
        what = f"perturb_sources(level={level})"
        expect(isinstance(out, SourceViews), f"{what} returned {type(out).__name__}, expected SourceViews")
        for name in ("rgb", "intrinsics", "c2w"):
            a, b = getattr(given, name), getattr(out, name)
            expect(isinstance(b, torch.Tensor) and b.shape == a.shape and b.dtype == a.dtype,
                   f"{what}: {name} is {getattr(b, 'shape', b)!r} {getattr(b, 'dtype', '')}, expected "
                   f"{list(a.shape)} {a.dtype}")
            expect(all_finite(b), f"{what}: {name} holds NaN or Inf")
        expect(float(out.rgb.min()) >= 0.0 and float(out.rgb.max()) <= 1.0,
               f"{what}: rgb in [{float(out.rgb.min()):.3g}, {float(out.rgb.max()):.3g}], expected [0, 1]")
        rotation = out.c2w[:, :3, :3].double()
        eye = torch.eye(3, dtype=torch.float64).expand_as(rotation)
        expect(torch.allclose(rotation @ rotation.transpose(1, 2), eye, atol=1e-4)
               and bool((torch.linalg.det(rotation) > 0).all())
               and torch.equal(out.c2w[:, 3], given.c2w[:, 3]),
               f"{what}: c2w is not a rigid camera-to-world pose (rotation orthonormal, det +1, last row 0 0 0 1)")


def check_determinism(case: StressCase) -> None:
    """The same generator seed gives the same perturbation."""
    for level in runnable_levels(case):
        _, first = _perturbed(case, level, 7, in_place_fails=False)
        _, again = _perturbed(case, level, 7, in_place_fails=False)
        expect(torch.equal(first.rgb, again.rgb) and torch.equal(first.c2w, again.c2w),
               f"perturb_sources(level={level}) differs between two calls with the same generator seed: draw "
               "randomness from the generator argument only")


CHECKS: dict[str, Callable[[StressCase], None]] = {
    "levels": check_levels,
    "sources": check_sources,
    "targets": check_targets,
    "perturbation": check_perturbation,
    "determinism": check_determinism,
}
