"""Checks of depth sources: ``belief(rays, sources, features) -> DepthBelief`` (``depths`` ``[R, D]`` ascending within
each ray's near and far, ``probabilities`` ``[R, D]`` summing to 1, ``evidence`` ``[R]`` bool), deterministic, finite,
without gradient, and flat where the source views cannot see the rays."""

from __future__ import annotations

from typing import Any

import torch

from gpnerf_core.geometry.ray_depth import DepthBelief
from gpnerf_core.testing.checks.common import (
    Subject, call, check_build, check_round_trip, expect, expect_finite, expect_sums_to_one, expect_tensor, shape,
)
from gpnerf_core.testing.inputs import images, ray_batch
from gpnerf_core.types import FeatureMaps, RayBatch, SourceViews

RAYS, VIEWS, HEIGHT, WIDTH, CHANNELS = 5, 3, 12, 16, 6
"""The kit's rays (``inputs.ray_batch``: a 16 x 12 camera at the origin, 0.5 m to 4 m), and source views of the same
size beside it, looking the same way."""


def kit_sources(*, behind: bool = False, seed: int = 0) -> tuple[SourceViews, FeatureMaps]:
    """Source views 0.1 m apart beside the kit's camera (``behind``: 10 m behind it, looking away, so they see none of
    its rays), with depth maps of a wall at 2 m (0 = unknown on a few pixels), and ``features`` whose maps require
    gradients (the pipeline's are trained)."""
    intrinsics = torch.tensor([[12.0, 0.0, 7.5], [0.0, 12.0, 5.5], [0.0, 0.0, 1.0]]).expand(VIEWS, 3, 3)
    c2w = torch.eye(4).repeat(VIEWS, 1, 1)
    c2w[:, 0, 3] = torch.tensor([-0.1, 0.05, 0.1])
    if behind:
        c2w[:, 2, 3] = -10.0
        c2w[:, :3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0]))
    depth = torch.full((VIEWS, HEIGHT, WIDTH), 2.0)
    depth[:, :2, :3] = 0.0
    sources = SourceViews(rgb=images(VIEWS, HEIGHT, WIDTH, seed=seed), intrinsics=intrinsics, c2w=c2w, depth=depth)
    g = torch.Generator().manual_seed(seed)
    maps = torch.randn(VIEWS, CHANNELS, HEIGHT // 2, WIDTH // 2, generator=g).requires_grad_()
    return sources, FeatureMaps(radiance=maps, semantic=None)


def belief(source: Any, rays: RayBatch, sources: SourceViews, features: FeatureMaps) -> DepthBelief:
    """The belief, checked against the interface: types, shapes, order, range and normalisation."""
    what = f"belief(rays [{rays.num_rays}], {VIEWS} source views, radiance {shape(features.radiance)})"
    out = call(what, source.belief, rays, sources, features)
    expect(isinstance(out, DepthBelief), f"{what} returned {type(out).__name__}, expected a DepthBelief")
    depths = expect_tensor(out.depths, f"{what}.depths")
    expect(depths.dim() == 2 and depths.shape[0] == rays.num_rays and depths.shape[1] >= 2,
           f"{what}.depths {shape(depths)}, expected [{rays.num_rays}, D] with D >= 2")
    expect_tensor(out.probabilities, f"{what}.probabilities", list(depths.shape))
    expect_tensor(out.evidence, f"{what}.evidence", [rays.num_rays], torch.bool)
    expect_finite({f"{what}.depths": depths, f"{what}.probabilities": out.probabilities}, "")
    expect(bool((depths[:, 1:] >= depths[:, :-1]).all()), f"{what}.depths are not ascending along each ray")
    inside = (depths >= rays.near[:, None] - 1e-5) & (depths <= rays.far[:, None] + 1e-5)
    expect(bool(inside.all()), f"{what}.depths leave the rays' [near, far] (min {float(depths.min()):.3g} m, max "
                               f"{float(depths.max()):.3g} m; rays from {float(rays.near.min()):.3g} to "
                               f"{float(rays.far.max()):.3g} m)")
    expect_sums_to_one(out.probabilities, -1, f"{what}.probabilities")
    return out


def check_belief(subject: Subject) -> None:
    """A belief of the right shapes, ascending depths within the rays' bounds, normalised probabilities (several
    rays, and one)."""
    source = subject.build()
    sources, features = kit_sources()
    belief(source, ray_batch(RAYS), sources, features)
    belief(source, ray_batch(1, seed=1), sources, features)


def check_no_gradient(subject: Subject) -> None:
    """It places samples and is not trained: no output requires grad, even from features that do."""
    source = subject.build()
    sources, features = kit_sources()
    out = belief(source, ray_batch(RAYS), sources, features)
    grads = [name for name in ("depths", "probabilities") if getattr(out, name).requires_grad]
    expect(not grads, f"belief(...).{', '.join(grads)} requires grad; a depth source places samples, detach it")


def check_determinism(subject: Subject) -> None:
    """The same inputs give the same belief, whatever torch's global random state."""
    source = subject.build()
    sources, features = kit_sources()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(1)
        first = belief(source, ray_batch(RAYS), sources, features)
        torch.manual_seed(2)
        second = belief(source, ray_batch(RAYS), sources, features)
    expect(torch.equal(first.depths, second.depths) and torch.equal(first.probabilities, second.probabilities),
           "belief(...) differs between two calls on the same inputs")


def check_unseen_rays(subject: Subject) -> None:
    """Rays no source view sees get a flat belief and no evidence (so the family spreads their samples)."""
    source = subject.build()
    sources, features = kit_sources(behind=True)
    out = belief(source, ray_batch(RAYS), sources, features)
    expect(not bool(out.evidence.any()), f"belief(...).evidence is {out.evidence.tolist()} for rays no view sees, "
                                         "expected all False")
    flat = torch.full_like(out.probabilities, 1.0 / out.probabilities.shape[-1])
    expect(torch.allclose(out.probabilities, flat, atol=1e-5),
           "belief(...).probabilities are not flat for rays no view sees (a guess where the views tell nothing)")


CHECKS = {
    "build": check_build,
    "belief": check_belief,
    "no gradient": check_no_gradient,
    "determinism": check_determinism,
    "unseen rays": check_unseen_rays,
    "config round trip": check_round_trip,
}
