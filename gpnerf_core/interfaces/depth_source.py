"""Interface of a depth source: a cheap depth per ray, from the source views, before any rendering pass."""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import Tensor

from gpnerf_core.geometry.ray_depth import DepthBelief
from gpnerf_core.geometry.sampling import surface_depths
from gpnerf_core.runtime.profiling import stage
from gpnerf_core.types import FeatureMaps, RayBatch, SourceViews


class DepthSource(ABC):
    """Where each ray's surface is likely to be, so a family renders a few samples there instead of many along the
    whole ray (``model.sampler=depth`` with ``+depth_source=<name>``; ENeRF's idea).

    A depth source places samples; it is not trained by the loss (no gradient flows through its belief) and may hold
    no parameters. The family turns the belief into samples (``gpnerf_core.geometry.surface_depths``: a few around a
    concentrated belief, spread by it where it is not), so a source that knows nothing about a ray returns a flat
    belief rather than a guess.
    """

    @abstractmethod
    def belief(self, rays: RayBatch, sources: SourceViews, features: FeatureMaps) -> DepthBelief:
        """The belief of ``rays`` (``R`` rays, each with its near and far) from the target's source views and their
        encoded ``features`` (the family's extractor output, ``[V, C, h, w]`` maps tiling each image).

        Returns:
            ``DepthBelief``: ``depths`` ``[R, D]`` ascending within each ray's ``[near, far]``, ``probabilities``
            ``[R, D]`` non-negative and summing to 1 per ray, ``evidence`` ``[R]`` bool; deterministic, finite, and
            without gradient.
        """

    def sample_depths(self, rays: RayBatch, sources: SourceViews, features: FeatureMaps, num_samples: int, *,
                      spread: float, uncertainty: float, perturb: bool,
                      generator: torch.Generator | None = None) -> Tensor:
        """``num_samples`` depths ``[R, N]`` per ray from this source's belief, for a family's one pass: evenly around
        the belief's depth where it is concentrated, drawn from it where it is flat (``surface_depths``, with its
        ``spread``, ``uncertainty``, ``perturb`` and ``generator``)."""
        with stage("depth sweep"):
            belief = self.belief(rays, sources, features)
        depths, _ = surface_depths(rays, belief.depths, belief.probabilities, num_samples, spread=spread,
                                   uncertainty=uncertainty, perturb=perturb, generator=generator)
        return depths
