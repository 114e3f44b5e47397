"""The semantic-embedding field rendered by reusing the transformers' attention (GP-NeRF, Sec. 3.2-3.3).

GP-NeRF aggregates the source views' semantic features with each field block's view attention A_b and mixes
them along the ray with each ray block's attention R_b, sums the blocks and averages over the samples of the
ray. Everything is linear in the semantic features F, so with

    W[r, s', v, a] = sum_b  mean_s R_b[r, h(a), s, s']  *  A_b[r, s', v, a]

the rendered feature is ``sum_{s', v} F[r, s', v, c] * W[r, s', v, g(c)]``: one pass over F instead of one per
block. ``g(c) = c // (C / A)`` maps a semantic channel to its attention channel and ``h(a) = a // (A / H)`` an
attention channel to its ray-attention head, so head h mixes the h-th block of semantic channels (one head per
pyramid level in GP-NeRF: 4 heads, 4 x 128 channels).
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

from gpnerf_core.errors import ConfigError


class SemanticFieldRenderer(nn.Module):
    """Renders per-ray (and optionally per-sample) semantic features from reused attention.

    Args:
        semantic_dim: C, channels of the source semantic maps.
        attention_channels: A, channels of the view attention; C must be a multiple of A.
        ray_heads: H, heads of the ray attention; A must be a multiple of H.
        num_blocks: B, transformer blocks whose attentions are summed.
        joint_attention: False detaches both attentions ("frozen attention", Table 4 ID 1), so semantic
            losses do not train the transformers.
        adaptor_relu: apply ReLU after the adaptor as the released code does. Off by default: the teacher
            features it is distilled to are signed (REFERENCE C4).
    """

    def __init__(
        self,
        *,
        semantic_dim: int,
        attention_channels: int,
        ray_heads: int,
        num_blocks: int,
        joint_attention: bool = True,
        adaptor_relu: bool = False,
    ) -> None:
        super().__init__()
        if semantic_dim % attention_channels:
            raise ConfigError(
                f"semantic width {semantic_dim} is not a multiple of the view attention's {attention_channels} "
                "channels; choose extractor and field aggregator widths so that it is"
            )
        if attention_channels % ray_heads:
            raise ConfigError(
                f"view attention channels {attention_channels} are not a multiple of the ray aggregator's "
                f"{ray_heads} heads"
            )
        self.semantic_dim = semantic_dim
        self.attention_channels = attention_channels
        self.expansion = semantic_dim // attention_channels
        self.ray_heads = ray_heads
        self.num_blocks = num_blocks
        self.joint_attention = joint_attention
        self.adaptor_relu = adaptor_relu
        self.adaptor = nn.Linear(semantic_dim, semantic_dim)
        # Start as the mean over blocks, so rendered features begin in the teacher's feature space.
        with torch.no_grad():
            self.adaptor.weight.copy_(torch.eye(semantic_dim) / num_blocks)
            self.adaptor.bias.zero_()

    def combined_weights(self, view_attention: Sequence[Tensor], ray_attention: Sequence[Tensor]) -> Tensor:
        """``W`` ``[R, S, V, A]`` from per-block view ``[R, S, V, A]`` and ray ``[R, H, S, S]`` attentions."""
        per_head = self.attention_channels // self.ray_heads
        weights = None
        for view, ray in zip(view_attention, ray_attention, strict=True):
            if not self.joint_attention:
                view, ray = view.detach(), ray.detach()
            column_mean = ray.mean(dim=2)  # [R, H, S]: how much each sample contributes, averaged over queries
            per_channel = column_mean.repeat_interleave(per_head, dim=1).transpose(1, 2)  # [R, S, A]
            term = view * per_channel[:, :, None, :]
            weights = term if weights is None else weights + term
        if weights is None:
            raise ConfigError("the transformers returned no attention blocks")
        return weights

    def forward(
        self,
        semantic: Tensor,
        view_attention: Sequence[Tensor],
        ray_attention: Sequence[Tensor],
        *,
        with_samples: bool = False,
    ) -> tuple[Tensor, Tensor | None]:
        """Render semantic features.

        Args:
            semantic: ``[R, S, V, C]`` source semantic features sampled at every ray sample.
            view_attention: B tensors ``[R, S, V, A]``.
            ray_attention: B tensors ``[R, H, S, S]``.
            with_samples: also return per-sample features ``sum_v F * sum_b A_b`` ``[R, S, C]`` for the D.G loss.

        Returns:
            ``[R, C]`` rendered features (after the adaptor) and the per-sample features or None.
        """
        num_rays, num_samples, num_views, channels = semantic.shape
        grouped = semantic.reshape(num_rays, num_samples, num_views, self.attention_channels, self.expansion)
        weights = self.combined_weights(view_attention, ray_attention)
        rendered = torch.einsum("rsvae,rsva->rae", grouped, weights).reshape(num_rays, channels)
        rendered = self.adaptor(rendered)
        if self.adaptor_relu:
            rendered = torch.relu(rendered)
        per_sample = None
        if with_samples:
            summed = view_attention[0]
            for view in view_attention[1:]:
                summed = summed + view
            if not self.joint_attention:
                summed = summed.detach()
            per_sample = torch.einsum("rsvae,rsva->rsae", grouped, summed).reshape(num_rays, num_samples, channels)
        return rendered, per_sample

    def reference_forward(self, semantic: Tensor, view_attention: Sequence[Tensor], ray_attention: Sequence[Tensor]) -> Tensor:
        """The block-by-block computation of the released code, before the adaptor; for tests and benchmarks.

        ``s_b = sum_v F * expand(A_b)``, ``t_b = R_b`` applied per head, ``mean_s sum_b t_b``.
        """
        num_rays, num_samples, _, channels = semantic.shape
        head_dim = channels // self.ray_heads
        total = torch.zeros(num_rays, num_samples, channels, dtype=semantic.dtype, device=semantic.device)
        for view, ray in zip(view_attention, ray_attention, strict=True):
            expanded = view.repeat_interleave(self.expansion, dim=-1)  # [R, S, V, C]
            s_b = (semantic * expanded).sum(dim=2)  # [R, S, C]
            heads = s_b.reshape(num_rays, num_samples, self.ray_heads, head_dim).transpose(1, 2)  # [R, H, S, c]
            t_b = (ray @ heads).transpose(1, 2).reshape(num_rays, num_samples, channels)
            total = total + t_b
        return total.mean(dim=1)
