"""Depths along rays: stratified in inverse depth (GNT's coarse samples) or in depth or 1/depth with NeRF's bin jitter
(``stratified_depths``), importance-sampled from weights (fine), and around a depth where the surfaces are."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from gpnerf_core.errors import ConfigError
from gpnerf_core.types import RayBatch, RaySamples

SAMPLERS = ("uniform", "depth")
"""``model.sampler`` values of the families that offer it."""


@dataclass(frozen=True)
class SurfaceSampling:
    """Where a family's last pass puts its samples (``model.sampler``, ``model.surface_spread``,
    ``model.surface_uncertainty``), checked when built.

    ``uniform``: the family's own sampling (GNT's coarse samples plus importance samples from the coarse weights).
    ``depth``: only a few samples per ray around a cheap depth, or spread by its belief where that depth is uncertain
    (``surface_depths``): from the family's own coarse pass, or, with a ``+depth_source`` (``DepthSource``: a sweep of
    the source views' features or recorded depth along the ray), from the source views alone: one pass.
    """

    sampler: str = "uniform"
    spread: float = 2.0
    """The samples span the depth +- this many standard deviations of the belief (at least one of its bins)."""
    uncertainty: float = 0.2
    """A ray whose belief's standard deviation exceeds this fraction of its depth gets samples drawn from the belief."""

    def __post_init__(self) -> None:
        if self.sampler not in SAMPLERS:
            raise ConfigError(f"model.sampler={self.sampler!r}; expected one of: {', '.join(SAMPLERS)}")
        if not (math.isfinite(self.spread) and self.spread > 0):
            raise ConfigError(f"model.surface_spread={self.spread!r}: expected a finite number of standard deviations > 0")
        if not (math.isfinite(self.uncertainty) and self.uncertainty > 0):
            raise ConfigError(f"model.surface_uncertainty={self.uncertainty!r}: expected a finite fraction of the "
                              "depth > 0")


def stratified_inverse_depths(
    rays: RayBatch, num_samples: int, *, perturb: bool, generator: torch.Generator | None = None
) -> Tensor:
    """``[R, S]`` ascending depths, uniform in 1/depth between near and far.

    Uniform steps in inverse depth put more samples close to the camera, as GNT's ``inv_uniform`` does for
    unbounded indoor scenes. With ``perturb`` each sample is jittered inside its bin (training);
    otherwise samples sit at bin edges deterministically (evaluation).
    """
    inv_near = 1.0 / rays.near[:, None]
    inv_far = 1.0 / rays.far[:, None]
    steps = torch.linspace(0.0, 1.0, num_samples, device=rays.near.device, dtype=rays.near.dtype)
    if perturb:
        jitter = torch.rand(
            (rays.num_rays, num_samples), generator=generator, device=rays.near.device, dtype=rays.near.dtype
        )
        steps = (steps + jitter / max(num_samples - 1, 1)).clamp(max=1.0)
    inverse = inv_near * (1.0 - steps) + inv_far * steps
    return torch.sort(1.0 / inverse, dim=-1).values


def stratified_depths(rays: RayBatch, num_samples: int, *, inverse: bool, generator: torch.Generator | None) -> Tensor:
    """``[R, S]`` ascending depths from near to far, uniform in depth (or 1/depth); with a ``generator`` each is drawn
    uniformly in its bin between the midpoints of its neighbours (NeRF's and MVSNeRF's ``perturb``)."""
    steps = torch.linspace(0.0, 1.0, num_samples, device=rays.near.device, dtype=rays.near.dtype)
    near, far = rays.near[:, None], rays.far[:, None]
    depths = 1.0 / (1.0 / near * (1.0 - steps) + 1.0 / far * steps) if inverse else near * (1.0 - steps) + far * steps
    if generator is None:
        return depths
    mids = 0.5 * (depths[:, 1:] + depths[:, :-1])
    upper, lower = torch.cat([mids, depths[:, -1:]], -1), torch.cat([depths[:, :1], mids], -1)
    return lower + (upper - lower) * torch.rand(depths.shape, generator=generator, device=depths.device,
                                                 dtype=depths.dtype)


def importance_depths(
    depths: Tensor,
    weights: Tensor,
    num_samples: int,
    *,
    deterministic: bool,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Draw ``num_samples`` extra depths ``[R, N]`` from the piecewise-constant pdf of ``weights``.

    The pdf lives on the bins between the midpoints of ``depths`` ``[R, S]``, using the interior weights
    ``weights[:, 1:-1]`` (as NeRF/GNT do); weights are detached, so no gradient flows through sampling.
    """
    weights = weights.detach()[:, 1:-1] + 1e-5
    mids = 0.5 * (depths[:, 1:] + depths[:, :-1])  # [R, S - 1] bin edges
    pdf = weights / weights.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1)  # [R, S - 1]
    if deterministic:
        u = torch.linspace(0.0, 1.0, num_samples, device=depths.device, dtype=depths.dtype)
        u = u.expand(depths.shape[0], num_samples).contiguous()
    else:
        u = torch.rand((depths.shape[0], num_samples), generator=generator, device=depths.device, dtype=depths.dtype)
    index = torch.searchsorted(cdf, u, right=True)
    below = (index - 1).clamp(min=0)
    above = index.clamp(max=cdf.shape[-1] - 1)
    cdf_lo, cdf_hi = cdf.gather(1, below), cdf.gather(1, above)
    bin_lo, bin_hi = mids.gather(1, below), mids.gather(1, above)
    span = torch.where(cdf_hi - cdf_lo < 1e-5, torch.ones_like(cdf_hi), cdf_hi - cdf_lo)
    t = (u - cdf_lo) / span
    return (bin_lo + t * (bin_hi - bin_lo)).detach()


def points_along_rays(rays: RayBatch, depths: Tensor) -> RaySamples:
    """World points ``origin + depth * direction`` for ``depths`` ``[R, S]`` (sorted here)."""
    depths = torch.sort(depths, dim=-1).values
    points = rays.origins[:, None, :] + depths[..., None] * rays.directions[:, None, :]
    return RaySamples(depths=depths, points=points)


def surface_depths(
    rays: RayBatch,
    depths: Tensor,
    weights: Tensor,
    num_samples: int,
    *,
    spread: float,
    uncertainty: float,
    perturb: bool,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """``num_samples`` depths ``[R, N]`` where a first pass saw the surface, and ``[R]`` bool: the ray's depth was
    certain (ENeRF's idea: a cheap depth, then a few samples around it, instead of samples along the whole ray).

    From a pass over ``depths`` ``[R, S]`` with compositing ``weights`` ``[R, S]`` (detached; normalised here): the
    expected depth ``d`` and the weights' spread ``sigma``. A certain ray (``sigma <= uncertainty * d``) gets its
    samples evenly in ``d +- h``, ``h = max(spread * sigma, the first pass's bin width at d)``, clipped to the ray's
    ``[near, far]``. An uncertain one (no surface, or several) falls back to importance samples of the first pass's
    weights (``importance_depths``: along the whole ray where the weights are flat, around each mode where there are
    several). ``perturb`` jitters each sample inside its bin (training), as ``stratified_inverse_depths`` does.
    """
    w = weights.detach().clamp_min(0)
    w = w / w.sum(dim=-1, keepdim=True).clamp_min(1e-8)
    mean = (w * depths).sum(dim=-1)
    sigma = (w * (depths - mean[:, None]) ** 2).sum(dim=-1).clamp_min(0).sqrt()
    bins = depths.shape[-1] - 1
    # inverse-depth bins are d^2 (1/near - 1/far) / bins wide at depth d
    bin_width = mean**2 * (1.0 / rays.near - 1.0 / rays.far) / max(bins, 1)
    half = torch.maximum(spread * sigma, bin_width)
    low = torch.maximum(mean - half, rays.near)
    high = torch.minimum(mean + half, rays.far)
    steps = torch.linspace(0.0, 1.0, num_samples, device=depths.device, dtype=depths.dtype).expand(rays.num_rays, -1)
    if perturb:
        jitter = torch.rand((rays.num_rays, num_samples), generator=generator, device=depths.device, dtype=depths.dtype)
        steps = (steps + jitter / max(num_samples - 1, 1)).clamp(max=1.0)
    around = low[:, None] + (high - low)[:, None] * steps
    certain = torch.isfinite(mean) & (sigma <= uncertainty * mean)
    spread_out = importance_depths(depths, weights, num_samples, deterministic=not perturb, generator=generator)
    chosen = torch.where(certain[:, None], around, spread_out)
    return torch.sort(chosen, dim=-1).values.detach(), certain
