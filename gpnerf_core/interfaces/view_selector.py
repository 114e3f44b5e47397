"""Interface of source-view selection."""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import Tensor


class ViewSelector(ABC):
    """Chooses the source views for a target camera."""

    @abstractmethod
    def select(
        self,
        target_c2w: Tensor,
        candidate_c2w: Tensor,
        num_views: int,
        generator: torch.Generator | None = None,
    ) -> list[int]:
        """Pick ``num_views`` rows of ``candidate_c2w`` ``[N, 4, 4]`` for ``target_c2w`` ``[4, 4]``.

        With ``generator`` None the choice is deterministic (evaluation); with a generator it may be
        randomized (training). Returns positions into ``candidate_c2w``; fewer than ``num_views`` only
        when there are fewer candidates.
        """
