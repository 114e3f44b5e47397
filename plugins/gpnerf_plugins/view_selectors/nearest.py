"""Source views nearest to the target camera by centre distance and viewing direction."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from gpnerf_core import ConfigError, DataError, NonFiniteError, ViewSelector


@dataclass
class NearestViewsConfig:
    name: str = "nearest"
    """Registry name of this view selector."""
    pool_factor: int = 2
    """Training picks k views at random among the pool_factor * k best; 1 = always the k best."""
    angle_weight: float = 0.5
    """Weight of the viewing-angle term (angle / pi) against the distance term (distance / largest distance)."""


class NearestViews(ViewSelector):
    """Ranks candidates by ``distance / max_distance + angle_weight * angle / pi``, lower is nearer.

    ``distance`` is between camera centres, ``max_distance`` the largest over the candidates, and ``angle``
    between the cameras' optical axes (OpenCV +z). Ties keep candidate order. Evaluation (no generator) takes
    the k best; training draws k without replacement from the ``pool_factor * k`` best. Either way the result is
    ordered best first and never repeats a candidate.
    """

    def __init__(self, pool_factor: int = 2, angle_weight: float = 0.5) -> None:
        if int(pool_factor) != pool_factor or pool_factor < 1:
            raise ConfigError(f"view_selector.pool_factor={pool_factor}; expected an integer >= 1")
        if not (math.isfinite(angle_weight) and angle_weight >= 0):
            raise ConfigError(f"view_selector.angle_weight={angle_weight}; expected a finite number >= 0")
        self.pool_factor = int(pool_factor)
        self.angle_weight = float(angle_weight)

    def scores(self, target_c2w: Tensor, candidate_c2w: Tensor) -> Tensor:
        """Score ``[N]`` of each candidate ``[N, 4, 4]`` for ``target_c2w`` ``[4, 4]``; lower is nearer."""
        if target_c2w.shape != (4, 4):
            raise DataError(f"target_c2w has shape {tuple(target_c2w.shape)}; expected (4, 4)")
        if candidate_c2w.ndim != 3 or candidate_c2w.shape[1:] != (4, 4):
            raise DataError(f"candidate_c2w has shape {tuple(candidate_c2w.shape)}; expected (N, 4, 4)")
        target = target_c2w.to(candidate_c2w)
        if not (torch.isfinite(target).all() and torch.isfinite(candidate_c2w).all()):
            raise NonFiniteError("a camera pose given to the nearest view selector contains NaN or Inf")
        distance = torch.linalg.vector_norm(candidate_c2w[:, :3, 3] - target[:3, 3], dim=-1)
        scale = distance.max().clamp_min(torch.finfo(distance.dtype).tiny)
        axes = torch.nn.functional.normalize(candidate_c2w[:, :3, 2], dim=-1)
        cosine = (axes @ torch.nn.functional.normalize(target[:3, 2], dim=0)).clamp(-1.0, 1.0)
        return distance / scale + self.angle_weight * torch.arccos(cosine) / math.pi

    def select(
        self,
        target_c2w: Tensor,
        candidate_c2w: Tensor,
        num_views: int,
        generator: torch.Generator | None = None,
    ) -> list[int]:
        if num_views < 1:
            raise ConfigError(f"num_views={num_views}; expected >= 1 source view")
        if candidate_c2w.shape[0] == 0:
            return []
        order = torch.sort(self.scores(target_c2w, candidate_c2w), stable=True).indices.cpu()
        count = min(num_views, len(order))
        if generator is None:
            return order[:count].tolist()
        pool = min(self.pool_factor * num_views, len(order))
        picked = torch.randperm(pool, generator=generator, device=generator.device)[:count].cpu()
        return order[picked.sort().values].tolist()
