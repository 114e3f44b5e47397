"""Interface of per-sample aggregators over source views (GNT's view transformer, GP-NeRF's FAT)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

from torch import Tensor, nn

from gpnerf_core.interfaces.weights import ImportsWeights
from gpnerf_core.types import FieldBlockOutput, ProjectedFeatures, RayBatch, RaySamples


class FieldAggregator(ImportsWeights, nn.Module, ABC):
    """Builds per-sample tokens by attending over the V source views, block by block.

    The pipeline interleaves its blocks with a ray aggregator's (block b of both, then block b + 1), as GNT
    does, and keeps every block's view attention: the semantic field is rendered from those attentions.
    Constructed with ``in_dim`` = 3 + the extractor's radiance width.
    """

    @property
    @abstractmethod
    def width(self) -> int:
        """Token width D."""

    @property
    @abstractmethod
    def attention_channels(self) -> int:
        """A: channels of the view attention (D for GNT's per-channel attention)."""

    @property
    @abstractmethod
    def num_blocks(self) -> int:
        """Number of blocks; must equal the ray aggregator's."""

    @abstractmethod
    def begin(self, features: ProjectedFeatures, samples: RaySamples, rays: RayBatch) -> tuple[Tensor, Any]:
        """Return the initial tokens ``[R, S, D]`` and a context every block reuses (e.g. per-view keys)."""

    @abstractmethod
    def block(self, index: int, tokens: Tensor, context: Any) -> FieldBlockOutput:
        """Run block ``index`` on ``tokens`` ``[R, S, D]``."""
