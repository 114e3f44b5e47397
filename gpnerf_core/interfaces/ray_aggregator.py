"""Interface of aggregators along each ray (GNT's ray transformer, GP-NeRF's RAT)."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor, nn

from gpnerf_core.interfaces.weights import ImportsWeights
from gpnerf_core.types import RayBlockOutput, RayReadout


class RayAggregator(ImportsWeights, nn.Module, ABC):
    """Mixes the S sample tokens of each ray by attention and reads out colour and weights.

    Constructed with ``in_dim`` = the field aggregator's token width. Every block returns its attention
    ``[R, H, S, S]``; the semantic renderer reuses it, one head per semantic level.
    """

    @property
    @abstractmethod
    def num_heads(self) -> int:
        """H: attention heads per block."""

    @property
    @abstractmethod
    def num_blocks(self) -> int:
        """Number of blocks; must equal the field aggregator's."""

    @abstractmethod
    def block(self, index: int, tokens: Tensor) -> RayBlockOutput:
        """Run block ``index`` on ``tokens`` ``[R, S, D]``."""

    @abstractmethod
    def readout(self, tokens: Tensor, last: RayBlockOutput) -> RayReadout:
        """Colour ``[R, 3]`` and sample weights ``[R, S]`` from the final tokens and the last block."""
