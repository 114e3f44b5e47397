"""GNT's ray transformer, GP-NeRF's Ray-Aggregation Transformer (RAT), as a ``RayAggregator``.

Multi-head scaled dot-product self-attention over the S samples of each ray, with no positional input,
then GNT's readout: colour from the mean over samples of the layer-normalised tokens (a linear layer and
NO sigmoid, so the colour is unbounded as in GNT: clamp it before metrics), and "weights" from the last
block's attention row of the first sample, averaged over heads.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import ConfigError, DataError, ImportedWeights, RayAggregator, RayBlockOutput, RayReadout
from gpnerf_plugins.transformers.common import (
    FeedForward, check_dropout, check_positive, maybe_dropout, softmax_last,
)
from gpnerf_plugins.transformers.gnt_weights import import_gnt_transformer

OWNER = "ray_aggregator gnt_ray"


@dataclass
class GNTRayTransformerConfig:
    """Options of the ``gnt_ray`` ray aggregator (``in_dim`` and ``num_blocks`` come from the field aggregator)."""

    name: str = "gnt_ray"
    """Registry name of this ray aggregator."""
    num_heads: int = 4
    """Attention heads H; the token width must be divisible by it (GP-NeRF: one head per FPN level)."""
    ff_ratio: int = 4
    """Hidden width of the feed-forward block, as a multiple of the token width."""
    dropout: float = 0.1
    """Dropout probability on the attention, the attention output and the feed-forward block."""


class RayAttention(nn.Module):
    """Multi-head self-attention over the samples of a ray (GNT ``Attention``, mode "qk").

    Parameter names match GNT's so its checkpoints load; q, k and v are computed by one matmul with the
    concatenated weights, the 1/sqrt(head width) scale folded into the query weight.
    """

    def __init__(self, dim: int, num_heads: int, dropout: float) -> None:
        super().__init__()
        self.q_fc = nn.Linear(dim, dim, bias=False)
        self.k_fc = nn.Linear(dim, dim, bias=False)
        self.v_fc = nn.Linear(dim, dim, bias=False)
        self.out_fc = nn.Linear(dim, dim)
        self.num_heads = num_heads
        self.dropout = dropout

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``x [R, S, D]`` (normalised) -> ``(out [R, S, D], attention [R, H, S, S])``, attention post-dropout."""
        R, S, D = x.shape
        H = self.num_heads
        scale = (D // H) ** -0.5
        weight = torch.cat((self.q_fc.weight * scale, self.k_fc.weight, self.v_fc.weight))
        q, k, v = F.linear(x, weight).view(R, S, 3, H, D // H).permute(2, 0, 3, 1, 4)  # each [R, H, S, D/H]
        attention = maybe_dropout(softmax_last(q @ k.transpose(-1, -2)), self.dropout, self.training)
        out = (attention @ v).transpose(1, 2).reshape(R, S, D)
        return maybe_dropout(self.out_fc(out), self.dropout, self.training), attention


class RayTransformerBlock(nn.Module):
    """Pre-LayerNorm block: tokens + self-attention along the ray, then + feed-forward (GNT ``Transformer``)."""

    def __init__(self, dim: int, num_heads: int, ff_hidden: int, dropout: float) -> None:
        super().__init__()
        self.attn_norm = nn.LayerNorm(dim, eps=1e-6)
        self.ff_norm = nn.LayerNorm(dim, eps=1e-6)
        self.ff = FeedForward(dim, ff_hidden, dropout)
        self.attn = RayAttention(dim, num_heads, dropout)

    def forward(self, tokens: Tensor) -> tuple[Tensor, Tensor]:
        """``tokens [R, S, D]`` -> ``(tokens [R, S, D], attention [R, H, S, S])``."""
        out, attention = self.attn(self.attn_norm(tokens))
        x = tokens + out
        return x + self.ff(self.ff_norm(x)), attention


class GNTRayTransformer(RayAggregator):
    """GNT's ray transformer (GP-NeRF's RAT) and its colour/weights readout.

    Submodule names follow GNT (``blocks`` for its ``view_selftrans``, ``norm``, ``rgb_fc``);
    ``split_gnt_state_dict`` maps a GNT checkpoint onto them.

    Args:
        in_dim: token width D (the field aggregator's width).
        num_blocks: number of blocks (the field aggregator's, so it is configured once).
        num_heads, ff_ratio, dropout: see ``GNTRayTransformerConfig``.
    """

    def __init__(
        self, *, in_dim: int, num_blocks: int, num_heads: int = 4, ff_ratio: int = 4, dropout: float = 0.1
    ) -> None:
        super().__init__()
        for key, value in (
            ("in_dim", in_dim),
            ("num_blocks", num_blocks),
            ("num_heads", num_heads),
            ("ff_ratio", ff_ratio),
        ):
            check_positive(OWNER, key, value)
        if in_dim % num_heads != 0:
            raise ConfigError(
                f"{OWNER}.num_heads={num_heads} does not divide the token width {in_dim}; "
                "expected a divisor of the field aggregator's width"
            )
        check_dropout(OWNER, dropout)
        self.in_dim = in_dim
        self.dropout = dropout
        self._num_heads = num_heads
        self.blocks = nn.ModuleList(
            RayTransformerBlock(in_dim, num_heads, in_dim * ff_ratio, dropout) for _ in range(num_blocks)
        )
        self.norm = nn.LayerNorm(in_dim)
        self.rgb_fc = nn.Linear(in_dim, 3)

    @property
    def num_heads(self) -> int:
        return self._num_heads

    @property
    def num_blocks(self) -> int:
        return len(self.blocks)

    def import_weights(self, checkpoint: Mapping[str, Any], fmt: str) -> ImportedWeights | None:
        """``fmt="gnt"``: this aggregator's share of an official GNT checkpoint's ``net_coarse``."""
        return import_gnt_transformer(checkpoint, "ray") if fmt == "gnt" else None

    def block(self, index: int, tokens: Tensor) -> RayBlockOutput:
        """Block ``index`` on ``tokens [R, S, D]`` -> ``RayBlockOutput(tokens, ray_attention [R, H, S, S])``."""
        if tokens.dim() != 3 or tokens.shape[-1] != self.in_dim:
            raise DataError(f"{OWNER}: tokens have shape {tuple(tokens.shape)}; expected [R, S, in_dim={self.in_dim}]")
        tokens, attention = self.blocks[index](tokens)
        return RayBlockOutput(tokens=tokens, ray_attention=attention)

    def readout(self, tokens: Tensor, last: RayBlockOutput) -> RayReadout:
        """Colour ``[R, 3]`` (unbounded) and weights ``[R, S]`` from the final tokens and the last block.

        The weights are row 0 (the first sample's query) of the last block's attention, averaged over heads.
        Without active dropout that is exactly GNT's; in training GNT uses the dropped-out row as is, which no
        longer sums to 1, so it is renormalised here to keep depth a convex combination of sample depths.
        """
        rgb = self.rgb_fc(self.norm(tokens).mean(dim=1))
        weights = last.ray_attention[:, :, 0].mean(dim=1)
        if self.training and self.dropout > 0.0:
            weights = weights / weights.sum(dim=-1, keepdim=True).clamp_min(torch.finfo(weights.dtype).tiny)
        return RayReadout(rgb=rgb, weights=weights)
