"""NeuRay's occlusion-aware aggregation network (IBRNet with NeuRay's visibility terms), Semantic-Ray's semantic head
and its Cross-Reprojection Attention.

Per pass, for R rays x S samples x V source views: the density and colour of every sample, and (with semantics) its
class scores, blended over the views with the colour weights (Semantic-Ray's "semantic ray construction").
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def sinusoidal_code(length: int, dim: int, *, device: torch.device, dtype: torch.dtype) -> Tensor:
    """``[length, dim]`` transformer position code of the index (sin on even, cos on odd channels), as IBRNet's
    ``PositionalEncoding`` built for the pass's own sample count."""
    position = torch.arange(length, device=device, dtype=dtype)[:, None]
    rates = torch.pow(10000.0, -2.0 * torch.div(torch.arange(dim, device=device), 2, rounding_mode="floor") / dim)
    angles = position * rates.to(dtype)
    return torch.where(torch.arange(dim, device=device) % 2 == 0, torch.sin(angles), torch.cos(angles))


class QueryMaskedAttention(nn.Module):
    """One multi-head attention layer of IBRNet, NeuRay and Semantic-Ray: bias-free q/k/v projections, scaled dot
    products, a residual and LayerNorm, no feed-forward.

    The official layers' ``[B, L, 1]`` mask masks *queries*: a masked row attends uniformly to every token, and masked
    tokens still act as keys. This keeps that behaviour.
    """

    def __init__(self, dim: int, heads: int = 4, head_dim: int = 4) -> None:
        super().__init__()
        self.heads, self.head_dim = heads, head_dim
        self.query = nn.Linear(dim, heads * head_dim, bias=False)
        self.key = nn.Linear(dim, heads * head_dim, bias=False)
        self.value = nn.Linear(dim, heads * head_dim, bias=False)
        self.out = nn.Linear(heads * head_dim, dim, bias=False)
        self.norm = nn.LayerNorm(dim, eps=1e-6)

    def forward(self, x: Tensor, query_mask: Tensor | None = None) -> Tensor:
        """``x`` ``[B, L, dim]``, ``query_mask`` ``[B, L]`` bool (False: the row attends uniformly) -> ``[B, L, dim]``."""
        batch, length, _ = x.shape

        def split(t: Tensor) -> Tensor:
            return t.view(batch, length, self.heads, self.head_dim).transpose(1, 2)

        scores = split(self.query(x)) @ split(self.key(x)).transpose(-1, -2) / math.sqrt(self.head_dim)
        if query_mask is not None:
            scores = scores.masked_fill(~query_mask[:, None, :, None], -1e9)
        mixed = (torch.softmax(scores, dim=-1) @ split(self.value(x))).transpose(1, 2).reshape(batch, length, -1)
        return self.norm(self.out(mixed) + x)


class CrossReprojectionAttention(nn.Module):
    """Semantic-Ray's CRA on the per-view features ``[R, S, V, D]`` of a ray's samples: intra-view (radial) attention
    along each view's reprojection of the ray, then cross-view attention among the V reprojections of each sample;
    one layer each, 4 heads of 4 dims (``use_ptrans``, ``ptrans_first: false``)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.radial = QueryMaskedAttention(dim)
        self.cross_view = QueryMaskedAttention(dim)

    def forward(self, features: Tensor, visible: Tensor) -> Tensor:
        """``features`` ``[R, S, V, D]``, ``visible`` ``[R, S, V]`` bool -> ``[R, S, V, D]``."""
        rays, samples, views, dim = features.shape
        code = sinusoidal_code(samples, dim, device=features.device, dtype=features.dtype)
        along = features.permute(0, 2, 1, 3).reshape(rays * views, samples, dim) + code
        seen_twice = (visible.sum(-1) > 1)[:, None, :].expand(rays, views, samples).reshape(rays * views, samples)
        along = self.radial(along, seen_twice).view(rays, views, samples, dim).permute(0, 2, 1, 3)
        across = self.cross_view(along.reshape(rays * samples, views, dim), visible.reshape(rays * samples, views))
        return across.view(rays, samples, views, dim)


def _weighted_mean_variance(x: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """IBRNet's ``fused_mean_variance`` over views (dim 2): ``sum w x`` and ``sum w (x - mean)^2``, the weights used
    as given (NeuRay's w0 is not renormalised)."""
    mean = (x * weights).sum(2, keepdim=True)
    return mean, (weights * (x - mean) ** 2).sum(2, keepdim=True)


class NeuRayAggregator(nn.Module):
    """``IBRNetWithNeuRay`` with Semantic-Ray's semantic head (and CRA when ``cross_reprojection``).

    Args:
        feature_dim: image-feature channels per view (the colour's 3 are added).
        visibility_dim: channels of the visibility embedding q.
        semantic_outputs: per-view semantic outputs: K class scores (label rendering) or the channels of the
            extractor's semantic maps (features a head decodes); 0: no semantic head.
        cross_reprojection: Semantic-Ray's CRA on BaseFC's output before the semantic head.
    """

    def __init__(self, feature_dim: int, visibility_dim: int, semantic_outputs: int, cross_reprojection: bool) -> None:
        super().__init__()
        per_view = 3 + feature_dim
        self.direction = nn.Sequential(nn.Linear(4, 16), nn.ELU(), nn.Linear(16, per_view), nn.ELU())
        self.probability_embedding = nn.Sequential(nn.Linear(visibility_dim + 2, visibility_dim), nn.ReLU(),
                                                   nn.Linear(visibility_dim, visibility_dim))
        self.neuray_weight = nn.Sequential(nn.Linear(visibility_dim, 8), nn.ELU(), nn.Linear(8, 1))
        self.base = nn.Sequential(nn.Linear(5 * per_view + visibility_dim, 64), nn.ELU(), nn.Linear(64, 32), nn.ELU())
        self.visibility = nn.Sequential(nn.Linear(32, 32), nn.ELU(), nn.Linear(32, 33), nn.ELU())
        self.visibility_refine = nn.Sequential(nn.Linear(32, 32), nn.ELU(), nn.Linear(32, 1))
        self.geometry = nn.Sequential(nn.Linear(2 * 32 + 1, 64), nn.ELU(), nn.Linear(64, 16), nn.ELU())
        self.ray_attention = QueryMaskedAttention(16)
        self.density_hidden = nn.Sequential(nn.Linear(16, 16), nn.ELU())
        self.density_out = nn.Linear(16, 1)
        self.blend = nn.Sequential(nn.Linear(32 + 1 + 4, 16), nn.ELU(), nn.Linear(16, 8), nn.ELU(), nn.Linear(8, 1))
        self.cross_reprojection = CrossReprojectionAttention(32) if cross_reprojection and semantic_outputs else None
        self.semantic_geometry = nn.Linear(16, 16) if semantic_outputs else None
        self.semantic_out = nn.Linear(16 + 16 + 32, semantic_outputs) if semantic_outputs else None

    def _base_input_layer(self, pooled: Tensor, features: Tensor, q: Tensor) -> Tensor:
        """BaseFC's first layer on ``[pooled, f_i, q_i]`` without materialising the view-expanded 207-channel input:
        its weight split by input block, the pooled block applied once per sample (the same function)."""
        layer, split = self.base[0], pooled.shape[-1]
        weight_pooled, weight_view, weight_q = layer.weight.split([split, features.shape[-1], q.shape[-1]], dim=1)
        return (F.linear(pooled, weight_pooled, layer.bias) + F.linear(features, weight_view)
                + F.linear(q, weight_q))

    def embed_probabilities(self, g: Tensor, hit: Tensor, vis: Tensor) -> Tensor:
        """q ``[..., visibility_dim]`` from G at the projection and its hit and visibility probabilities."""
        return self.probability_embedding(torch.cat([g, 2.0 * hit[..., None] - 1.0, 2.0 * vis[..., None] - 1.0], -1))

    def forward(self, rgb_features: Tensor, directions: Tensor, visible: Tensor, q: Tensor,
                semantics: bool) -> tuple[Tensor, Tensor, Tensor | None]:
        """One pass's samples.

        Args:
            rgb_features: ``[R, S, V, 3 + C]`` source colour and image features at the projections (0 where unseen).
            directions: ``[R, S, V, 4]`` NeuRay's direction features (difference of the unit directions to the source
                and target cameras, and their dot product).
            visible: ``[R, S, V]`` bool, the projection lands in front of the camera, inside the image.
            q: ``[R, S, V, visibility_dim]`` the visibility embedding.
            semantics: also return the semantic outputs.

        Returns:
            density ``[R, S]`` (0 where no view sees the sample), colour ``[R, S, 3]`` and the semantic outputs
            ``[R, S, semantic_outputs]`` blended over the views with the colour weights (or None).
        """
        mask = visible[..., None].to(rgb_features.dtype)  # [R, S, V, 1]
        colours = rgb_features[..., :3]
        features = rgb_features + self.direction(directions)
        weights = mask / (mask.sum(2, keepdim=True) + 1e-8)
        neuray_weights = torch.sigmoid(self.neuray_weight(q)) * weights
        pooled = torch.cat([*_weighted_mean_variance(features, neuray_weights),
                            *_weighted_mean_variance(features, weights)], -1)  # [R, S, 1, 4 (3 + C)]
        views = features.shape[2]
        x = self.base[1:](self._base_input_layer(pooled, features, q))  # [R, S, V, 32]
        before_residual = x
        residual_and_logit = self.visibility(x * weights)
        x = x + residual_and_logit[..., :32]
        visibility = torch.sigmoid(residual_and_logit[..., 32:]) * mask
        visibility = torch.sigmoid(self.visibility_refine(x * visibility)) * mask
        view_weights = visibility / (visibility.sum(2, keepdim=True) + 1e-8)
        mean, variance = _weighted_mean_variance(x, view_weights)
        g = self.geometry(torch.cat([mean[:, :, 0], variance[:, :, 0], view_weights.mean(2)], -1))  # [R, S, 16]
        seen_by = mask[..., 0].sum(-1)  # [R, S]
        samples = g.shape[1]
        g = g + sinusoidal_code(samples, g.shape[-1], device=g.device, dtype=g.dtype)
        g = self.ray_attention(g, seen_by > 1)
        hidden = self.density_hidden(g)
        density = F.relu(self.density_out(hidden)[..., 0]).masked_fill(seen_by < 1, 0.0)
        blend = self.blend(torch.cat([x, visibility, directions], -1)).masked_fill(mask == 0, -1e9)
        blend = torch.softmax(blend, dim=2)  # [R, S, V, 1]
        colour = (colours * blend).sum(2)
        scores = None
        if semantics and self.semantic_out is not None:
            per_view = before_residual
            if self.cross_reprojection is not None:
                per_view = self.cross_reprojection(before_residual, visible)
            ray_part = torch.cat([self.semantic_geometry(g), hidden], -1)[:, :, None].expand(-1, -1, views, -1)
            scores = (self.semantic_out(torch.cat([ray_part, per_view], -1)) * blend).sum(2)  # [R, S, K]
        return density, colour, scores
