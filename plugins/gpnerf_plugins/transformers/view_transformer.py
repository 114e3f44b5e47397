"""GNT's view transformer, GP-NeRF's Field-Aggregation Transformer (FAT), as a ``FieldAggregator``.

Each sample's token attends over the V source views with GNT's subtraction-based, per-channel attention.
Kept GNT quirks, needed to load its weights and reproduce its outputs:

* the initial token is the max over views of the per-view features, NOT masked by visibility, so views that
  miss the sample (zero-padded features) still take part in it;
* the values are projected from the projected keys (``V = v_fc(k_fc(f))``), not from the features;
* points enter the positional encoding as raw world coordinates (no scene normalisation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import (
    ConfigError,
    DataError,
    FieldAggregator,
    FieldBlockOutput,
    ImportedWeights,
    ProjectedFeatures,
    RayBatch,
    RaySamples,
    fractions,
    one_fewer_or_halved,
    size_knob,
)
from gpnerf_plugins.transformers.common import (
    FeedForward,
    check_dropout,
    linear_rows,
    check_positive,
    encoding_dim,
    masking_value,
    maybe_dropout,
    positional_encoding,
)
from gpnerf_plugins.transformers.gnt_weights import import_gnt_transformer

OWNER = "field_aggregator gnt_view"


@dataclass
class GNTViewTransformerConfig:
    """Options of the ``gnt_view`` field aggregator (``in_dim`` comes from the pipeline)."""

    name: str = "gnt_view"
    """Registry name of this field aggregator."""
    width: int = size_knob(64, "transformer width", fractions(8, 8, 0.75, 0.5))  # 8s: ray heads, D // 8
    """Token width D (GNT ``netwidth``); also the number of attention channels."""
    num_blocks: int = size_knob(8, "transformer blocks", one_fewer_or_halved)
    """Number of view-transformer blocks (GNT ``trans_depth``); the ray aggregator gets the same number."""
    ff_ratio: int = 4
    """Hidden width of the feed-forward block, as a multiple of D."""
    attn_hidden_ratio: int = 8
    """Hidden width of the attention MLP and of the pose MLP is D // attn_hidden_ratio."""
    dropout: float = 0.1
    """Dropout probability on the attention, the attention output and the feed-forward block."""
    pos_frequencies: int = 10
    """NeRF positional-encoding frequencies for points and view directions (encoding width 3 + 6F)."""


@dataclass(frozen=True)
class GNTViewContext:
    """What ``begin`` prepares once and every block reuses.

    Attributes:
        view_features: ``[R, S, V, D]`` per-view features after the input MLP (the keys' source).
        ray_diff: ``[R, S, V, 4]`` pose feature of each view (see ``ProjectedFeatures``).
        visible: ``[R, S, V]`` bool visibility of the sample in each view.
        hidden: ``[R, S, V, 1]`` bool, True where a view misses the sample; None when every view sees every sample.
        point_encoding: ``[R, S, 3 + 6F]`` encoding of the samples' world positions.
        direction_encoding: ``[R, 3 + 6F]`` encoding of the unit ray directions (shared by a ray's samples).
    """

    view_features: Tensor
    ray_diff: Tensor
    visible: Tensor
    hidden: Tensor | None
    point_encoding: Tensor
    direction_encoding: Tensor


class ViewAttention(nn.Module):
    """GNT's subtraction-based attention over views, separate for each of the D channels.

    With Q = q_fc(x), K = k_fc(f), V = v_fc(K) and P = pos_fc(ray_diff) (all ``[.., D]``):
    A = softmax_V(attn_fc(K - Q + P)) with hidden views masked, out = out_fc(sum_V (V + P) * A).

    Parameter names match GNT's ``Attention2D`` so its checkpoints load. The forward pass computes the same
    function with fewer passes over the ``[R, S, V, D]`` tensors: the linear maps are composed before they
    touch the per-view features, so K and P are never materialised and Q enters as a per-sample bias of
    the attention MLP's first layer. The last bias of ``attn_fc`` adds the same value to every view of a
    channel, so the softmax cancels it: its gradient is zero (as in GNT).
    """

    def __init__(self, dim: int, hidden: int, dropout: float) -> None:
        super().__init__()
        self.q_fc = nn.Linear(dim, dim, bias=False)
        self.k_fc = nn.Linear(dim, dim, bias=False)
        self.v_fc = nn.Linear(dim, dim, bias=False)
        self.pos_fc = nn.Sequential(nn.Linear(4, hidden), nn.ReLU(), nn.Linear(hidden, dim))
        self.attn_fc = nn.Sequential(nn.Linear(dim, hidden), nn.ReLU(), nn.Linear(hidden, dim))
        self.out_fc = nn.Linear(dim, dim)
        self.dropout = dropout

    def forward(self, x: Tensor, context: GNTViewContext) -> tuple[Tensor, Tensor]:
        """Attend over views.

        Args:
            x: ``[R, S, D]`` layer-normalised tokens (the queries' source).
            context: the per-view features, pose features and visibility.

        Returns:
            ``(out [R, S, D], attention [R, S, V, D])``, the attention post-dropout as it weighted the values.
        """
        feats = context.view_features
        R, S, V, D = feats.shape
        f = feats.reshape(-1, D)  # [N, D], N = R * S * V; kept 2-D so in-place ops below touch no views
        w_k, w_v = self.k_fc.weight, self.v_fc.weight
        pos_in, pos_out = self.pos_fc[0], self.pos_fc[2]
        att_in, att_out = self.attn_fc[0], self.attn_fc[2]

        pose_hidden = linear_rows(context.ray_diff.reshape(-1, 4), pos_in).relu_()  # [N, h]
        # V + P = f (Wv Wk)^T + pose_hidden Wp^T + bp, accumulated into one buffer.
        values = torch.addmm(pos_out.bias, f, (w_v @ w_k).t())
        values.addmm_(pose_hidden, pos_out.weight.t().to(values.dtype).contiguous())  # in-place: no autocast
        # First attention layer on K - Q + P, split into its per-view terms and a per-sample bias.
        hidden = f @ (att_in.weight @ w_k).t()
        hidden.addmm_(pose_hidden, (att_in.weight @ pos_out.weight).t())
        sample_bias = F.linear(x, -(att_in.weight @ self.q_fc.weight), att_in.bias + att_in.weight @ pos_out.bias)
        hidden = (hidden.view(R * S, V, -1) + sample_bias.view(R * S, 1, -1)).relu_()
        logits = linear_rows(hidden.view(R * S * V, -1), att_out)  # [N, D]
        if context.hidden is not None:
            logits.masked_fill_(context.hidden.reshape(-1, 1), masking_value(logits.dtype))
        attention = torch.softmax(logits.view(R, S, V, D), dim=2)
        attention = maybe_dropout(attention, self.dropout, self.training)
        out = torch.linalg.vecdot(values.view(R, S, V, D), attention, dim=2)
        return maybe_dropout(self.out_fc(out), self.dropout, self.training), attention


class ViewTransformerBlock(nn.Module):
    """Pre-LayerNorm block: tokens + attention over views, then + feed-forward (GNT ``Transformer2D``)."""

    def __init__(self, dim: int, attn_hidden: int, ff_hidden: int, dropout: float) -> None:
        super().__init__()
        self.attn_norm = nn.LayerNorm(dim, eps=1e-6)
        self.ff_norm = nn.LayerNorm(dim, eps=1e-6)
        self.ff = FeedForward(dim, ff_hidden, dropout)
        self.attn = ViewAttention(dim, attn_hidden, dropout)

    def forward(self, tokens: Tensor, context: GNTViewContext) -> tuple[Tensor, Tensor]:
        """``tokens [R, S, D]`` -> ``(tokens [R, S, D], attention [R, S, V, D])``."""
        out, attention = self.attn(self.attn_norm(tokens), context)
        x = tokens + out
        return x + self.ff(self.ff_norm(x)), attention


class GNTViewTransformer(FieldAggregator):
    """GNT's view transformer (GP-NeRF's FAT).

    Submodule names follow GNT (``rgbfeat_fc``, ``q_fcs``, and ``blocks`` for its ``view_crosstrans``);
    ``split_gnt_state_dict`` maps a GNT checkpoint onto them.

    Args:
        in_dim: width of ``ProjectedFeatures.rgb_features`` (3 + radiance width; GNT: 35).
        width, num_blocks, ff_ratio, attn_hidden_ratio, dropout, pos_frequencies: see
            ``GNTViewTransformerConfig``.
    """

    def __init__(
        self,
        *,
        in_dim: int,
        width: int = 64,
        num_blocks: int = 8,
        ff_ratio: int = 4,
        attn_hidden_ratio: int = 8,
        dropout: float = 0.1,
        pos_frequencies: int = 10,
    ) -> None:
        super().__init__()
        for key, value in (
            ("in_dim", in_dim),
            ("width", width),
            ("num_blocks", num_blocks),
            ("ff_ratio", ff_ratio),
            ("attn_hidden_ratio", attn_hidden_ratio),
        ):
            check_positive(OWNER, key, value)
        if width < attn_hidden_ratio:
            raise ConfigError(
                f"{OWNER}.attn_hidden_ratio={attn_hidden_ratio} exceeds width={width}; "
                "expected width // attn_hidden_ratio >= 1"
            )
        if isinstance(pos_frequencies, bool) or not isinstance(pos_frequencies, int) or pos_frequencies < 0:
            raise ConfigError(f"{OWNER}.pos_frequencies must be a non-negative integer, got {pos_frequencies!r}")
        check_dropout(OWNER, dropout)
        self.in_dim = in_dim
        self.pos_frequencies = pos_frequencies
        self._width = width
        encoding = encoding_dim(pos_frequencies)
        self.rgbfeat_fc = nn.Sequential(nn.Linear(in_dim, width), nn.ReLU(), nn.Linear(width, width))
        self.blocks = nn.ModuleList(
            ViewTransformerBlock(width, width // attn_hidden_ratio, width * ff_ratio, dropout)
            for _ in range(num_blocks)
        )
        # Even blocks re-inject position and direction: MLP(concat(token, enc(point), enc(direction))).
        self.q_fcs = nn.ModuleList(
            nn.Sequential(nn.Linear(width + 2 * encoding, width), nn.ReLU(), nn.Linear(width, width))
            if index % 2 == 0
            else nn.Identity()
            for index in range(num_blocks)
        )

    @property
    def width(self) -> int:
        return self._width

    @property
    def attention_channels(self) -> int:
        return self._width

    @property
    def num_blocks(self) -> int:
        return len(self.blocks)

    def import_weights(self, checkpoint: Mapping[str, Any], fmt: str) -> ImportedWeights | None:
        """``fmt="gnt"``: this aggregator's share of an official GNT checkpoint's ``net_coarse``."""
        return import_gnt_transformer(checkpoint, "field") if fmt == "gnt" else None

    def begin(
        self, features: ProjectedFeatures, samples: RaySamples, rays: RayBatch
    ) -> tuple[Tensor, GNTViewContext]:
        """Project the per-view features and take the initial tokens.

        Returns:
            ``(tokens [R, S, D], context)``; tokens are the max over ALL views of the projected per-view
            features (GNT's unmasked max-pool).
        """
        rgb_features = features.rgb_features
        if rgb_features.dim() != 4 or rgb_features.shape[-1] != self.in_dim:
            raise DataError(
                f"{OWNER}: ProjectedFeatures.rgb_features has shape {tuple(rgb_features.shape)}; "
                f"expected [R, S, V, in_dim={self.in_dim}]"
            )
        R, S, V, _ = rgb_features.shape
        if tuple(features.ray_diff.shape) != (R, S, V, 4):
            raise DataError(
                f"{OWNER}: ProjectedFeatures.ray_diff has shape {tuple(features.ray_diff.shape)}; "
                f"expected {(R, S, V, 4)}"
            )
        if tuple(features.visible.shape) != (R, S, V):
            raise DataError(
                f"{OWNER}: ProjectedFeatures.visible has shape {tuple(features.visible.shape)}; "
                f"expected {(R, S, V)}"
            )
        if tuple(samples.points.shape) != (R, S, 3) or tuple(rays.directions.shape) != (R, 3):
            raise DataError(
                f"{OWNER}: samples.points {tuple(samples.points.shape)} / rays.directions "
                f"{tuple(rays.directions.shape)} do not match R={R}, S={S}; expected [R, S, 3] / [R, 3]"
            )

        first, last = self.rgbfeat_fc[0], self.rgbfeat_fc[2]
        rows = linear_rows(rgb_features.reshape(-1, self.in_dim), first).relu_()
        view_features = linear_rows(rows, last).view(R, S, V, self._width)
        tokens = view_features.amax(dim=2)
        visible = features.visible.bool()
        hidden = None if bool(visible.all()) else (~visible)[..., None]
        dtype = view_features.dtype
        # sin(2^9 x) of metre coordinates needs float32 at least: bfloat16 would turn it into noise.
        encoding_dtype = torch.promote_types(dtype, torch.float32)
        directions = rays.directions.to(encoding_dtype)
        directions = directions / directions.norm(dim=-1, keepdim=True)
        context = GNTViewContext(
            view_features=view_features,
            ray_diff=features.ray_diff.to(dtype),
            visible=visible,
            hidden=hidden,
            point_encoding=positional_encoding(samples.points.to(encoding_dtype), self.pos_frequencies),
            direction_encoding=positional_encoding(directions, self.pos_frequencies),
        )
        return tokens, context

    def block(self, index: int, tokens: Tensor, context: GNTViewContext) -> FieldBlockOutput:
        """Block ``index``: attention over views and feed-forward, then (even blocks) the query update.

        Returns:
            ``FieldBlockOutput(tokens [R, S, D], view_attention [R, S, V, D])``.
        """
        tokens, attention = self.blocks[index](tokens, context)
        if index % 2 == 0:
            tokens = self._update_query(self.q_fcs[index], tokens, context)
        return FieldBlockOutput(tokens=tokens, view_attention=attention)

    def _update_query(self, mlp: nn.Sequential, tokens: Tensor, context: GNTViewContext) -> Tensor:
        """``MLP(concat(tokens, enc(point), enc(direction)))`` without building the concatenation.

        The first layer's weight is split by input block, so the direction term is computed once per ray.
        """
        first, last = mlp[0], mlp[2]
        width, encoding = self._width, context.point_encoding.shape[-1]
        weight = first.weight
        h = F.linear(tokens, weight[:, :width], first.bias)
        h = h + F.linear(context.point_encoding, weight[:, width : width + encoding])
        h = h + F.linear(context.direction_encoding, weight[:, width + encoding :])[:, None]
        return last(F.relu(h, inplace=True))
