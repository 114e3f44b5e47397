"""The semantic-embedding field rendered by reusing the transformers' attention (GP-NeRF, Sec. 3.2-3.3).

GP-NeRF aggregates the source views' semantic features with each field block's view attention A_b and mixes
them along the ray with each ray block's attention R_b, sums the blocks and averages over the samples of the
ray. Everything is linear in the semantic features F, so with

    W[r, s', v, a] = sum_b  mean_s R_b[r, h(a), s, s']  *  A_b[r, s', v, a]

the rendered feature is ``sum_{s', v} F[r, s', v, c] * W[r, s', v, g(c)]``: one pass over F instead of one per
block. ``g(c) = c // (C / A)`` maps a semantic channel to its attention channel and ``h(a) = a // (A / H)`` an
attention channel to its ray-attention head, so head h mixes the h-th block of semantic channels (one head per
pyramid level in GP-NeRF: 4 heads, 4 x 128 channels).

F itself (``[R, S, V, C]``, 512 channels) is the largest tensor of the model. When no gradient flows into the source
maps (the paper's setup: they are detached), the pass over F streams view by view (``StreamedRendering``): each view's
features are sampled, weighted and summed, and never all held at once; backward samples them again (or keeps them,
``recompute_samples=False``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import Tensor, nn

from gpnerf_core import ConfigError
from gpnerf_core import SampledMaps


class StreamedRendering(torch.autograd.Function):
    """``sum_{s, v} F * W`` (and ``sum_v F * W_s`` per sample) with F read one source view at a time.

    Forward inputs: ``weights`` ``[R, S, V, A]``, ``sample_weights`` ``[R, S, V, A]`` or None, ``sampled``
    (``SampledMaps``, C = A * expansion channels, no gradient), ``expansion``, ``recompute``. Outputs ``[R, C]`` and
    ``[R, S, C]`` (or None), in float32 or wider (autocast off inside: the sums run over S x V terms). Gradients
    flow to the two weight tensors only. Internally each view's features are ``[A, E, R, S]``, the layout
    ``grid_sample`` writes, so no per-view copy is made.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        weights: Tensor,
        sample_weights: Tensor | None,
        sampled: SampledMaps,
        expansion: int,
        recompute: bool,
    ) -> tuple[Tensor, Tensor | None]:
        rays, samples, views, attention = weights.shape
        # The sum runs over S x V terms: at least float32 whatever autocast would choose, and the same dtype in
        # backward (which runs outside autocast).
        dtype = torch.promote_types(torch.promote_types(weights.dtype, sampled.maps.dtype), torch.float32)
        rendered = per_sample = samples_by_view = None
        kept = []
        with torch.autocast(weights.device.type, enabled=False):
            # One copy of the weights into per-view contiguous [A, R, S] slices: reading them strided from
            # [R, S, V, A] inside the per-view products costs more than the products (5x here). ``.contiguous()``:
            # ``.to(dtype, memory_format=...)`` returns the permuted view itself when the dtype already matches.
            weights_by_view = weights.permute(2, 3, 0, 1).to(dtype).contiguous()
            if sample_weights is not None:
                samples_by_view = sample_weights.permute(2, 3, 0, 1).to(dtype).contiguous()
            for view in range(views):
                features = sampled.view(view, dtype).view(attention, expansion, rays, samples)
                term = torch.linalg.vecdot(features, weights_by_view[view][:, None], dim=-1)  # [A, E, R]
                rendered = term if rendered is None else rendered.add_(term)
                if samples_by_view is not None:
                    weight = samples_by_view[view][:, None]  # [A, 1, R, S]
                    per_sample = features * weight if per_sample is None else per_sample.addcmul_(features, weight)
                if not recompute:
                    kept.append(features)
        ctx.sampled, ctx.kept, ctx.expansion, ctx.compute_dtype = sampled, kept, expansion, dtype
        ctx.shape = (rays, samples, views, attention)
        ctx.dtypes = (weights.dtype, None if sample_weights is None else sample_weights.dtype)
        channels = attention * expansion
        rendered_out = rendered.permute(2, 0, 1).reshape(rays, channels)
        per_sample_out = None if per_sample is None else per_sample.permute(2, 3, 0, 1).reshape(rays, samples, channels)
        return rendered_out, per_sample_out

    @staticmethod
    def backward(ctx: Any, grad_rendered: Tensor | None, grad_per_sample: Tensor | None) -> tuple[Any, ...]:
        rays, samples, views, attention = ctx.shape
        expansion = ctx.expansion
        want_weights = ctx.needs_input_grad[0] and grad_rendered is not None
        want_samples = ctx.needs_input_grad[1] and grad_per_sample is not None
        if want_weights:
            grad_rendered = grad_rendered.reshape(rays, attention, expansion).permute(1, 2, 0)[..., None]  # [A, E, R, 1]
            grad_rendered = grad_rendered.to(ctx.compute_dtype)
        if want_samples:
            grad_per_sample = grad_per_sample.reshape(rays, samples, attention, expansion).permute(2, 3, 0, 1)
            grad_per_sample = grad_per_sample.to(ctx.compute_dtype).contiguous()
        grad_weights = grad_sample_weights = None
        for view in range(views):
            if not (want_weights or want_samples):
                break
            if ctx.kept:
                features = ctx.kept[view]
            else:
                features = ctx.sampled.view(view, ctx.compute_dtype).view(attention, expansion, rays, samples)
            if want_weights:
                if grad_weights is None:
                    grad_weights = grad_rendered.new_empty(views, attention, rays, samples, dtype=ctx.dtypes[0])
                grad_weights[view] = torch.linalg.vecdot(features, grad_rendered, dim=1).to(ctx.dtypes[0])
            if want_samples:
                if grad_sample_weights is None:
                    grad_sample_weights = grad_per_sample.new_empty(views, attention, rays, samples, dtype=ctx.dtypes[1])
                grad_sample_weights[view] = torch.linalg.vecdot(features, grad_per_sample, dim=1).to(ctx.dtypes[1])
        ctx.kept = []
        # Contiguous [R, S, V, A], the attention's own layout: a permuted gradient made the transformers' whole
        # backward stride through memory (paper-size step 6.0 -> 5.2 s; the same values).
        return (
            None if grad_weights is None else grad_weights.permute(2, 3, 0, 1).contiguous(),
            None if grad_sample_weights is None else grad_sample_weights.permute(2, 3, 0, 1).contiguous(),
            None,
            None,
            None,
        )


@dataclass
class AttentionSums:
    """The attention sums the semantic field needs, added block by block (``SemanticFieldRenderer.add_block``) so no
    block's attention is held for it: ``weights`` W ``[R, S, V, A]`` (see above) and, ``with_samples``, the plain sum
    ``sum_b A_b`` ``[R, S, V, A]`` that weights the per-sample features."""

    with_samples: bool
    weights: Tensor | None = None
    sample_weights: Tensor | None = None
    blocks: int = 0

    def checked(self) -> AttentionSums:
        if self.weights is None:
            raise ConfigError("the transformers returned no attention blocks")
        return self


def weight_term(view: Tensor, ray: Tensor, per_head: int) -> Tensor:
    """One block's share of W: ``view [R, S, V, A] * mean_queries(ray [R, H, S, S])`` expanded to A channels."""
    column_mean = ray.mean(dim=2)  # [R, H, S]: how much each sample contributes, averaged over queries
    per_channel = column_mean.repeat_interleave(per_head, dim=1).transpose(1, 2)  # [R, S, A]
    return view * per_channel[:, :, None, :]


@functools.lru_cache(maxsize=None)
def compiled_weight_term(backend: str):
    """``weight_term`` compiled with ``backend``, one wrapper per backend."""
    return torch.compile(weight_term, backend=backend)


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
        self._weight_term = weight_term

    def compile_sums(self, backend: str | None) -> None:
        """``torch.compile`` the per-block attention product (``add_block``) with ``backend`` (None: eager)."""
        self._weight_term = weight_term if backend is None else compiled_weight_term(backend)

    def add_block(self, total: AttentionSums, view: Tensor, ray: Tensor) -> None:
        """Add one block's view ``[R, S, V, A]`` and ray ``[R, H, S, S]`` attention to ``total`` (in place)."""
        if not self.joint_attention:
            view, ray = view.detach(), ray.detach()
        term = self._weight_term(view, ray, self.attention_channels // self.ray_heads)
        total.weights = term if total.weights is None else total.weights.add_(term)
        if total.with_samples:
            # The attention itself is saved for its own backward: never accumulate into it.
            total.sample_weights = view.clone() if total.sample_weights is None else total.sample_weights.add_(view)
        total.blocks += 1

    def combined_weights(self, view_attention: Sequence[Tensor], ray_attention: Sequence[Tensor]) -> Tensor:
        """``W`` ``[R, S, V, A]`` from per-block view ``[R, S, V, A]`` and ray ``[R, H, S, S]`` attentions."""
        total = AttentionSums(with_samples=False)
        for view, ray in zip(view_attention, ray_attention, strict=True):
            self.add_block(total, view, ray)
        return total.checked().weights

    def forward(
        self,
        semantic: Tensor | SampledMaps,
        view_attention: Sequence[Tensor],
        ray_attention: Sequence[Tensor],
        *,
        with_samples: bool = False,
        recompute_samples: bool = True,
    ) -> tuple[Tensor, Tensor | None]:
        """Render semantic features from every block's attention (see ``render``).

        Args:
            view_attention: B tensors ``[R, S, V, A]``.
            ray_attention: B tensors ``[R, H, S, S]``.
        """
        total = AttentionSums(with_samples=with_samples)
        for view, ray in zip(view_attention, ray_attention, strict=True):
            self.add_block(total, view, ray)
        return self.render(semantic, total, recompute_samples=recompute_samples)

    def render(
        self, semantic: Tensor | SampledMaps, total: AttentionSums, *, recompute_samples: bool = True
    ) -> tuple[Tensor, Tensor | None]:
        """Render semantic features from the attention sums of every block.

        Args:
            semantic: the source semantic features at every ray sample: ``SampledMaps`` from the projector, or a
                dense ``[R, S, V, C]`` tensor.
            total: ``add_block`` applied to every block; ``with_samples`` also returns per-sample features
                ``sum_v F * sum_b A_b`` ``[R, S, C]`` for the D.G loss.
            recompute_samples: when streaming, sample F again in backward instead of keeping it (less memory).

        Returns:
            ``[R, C]`` rendered features (after the adaptor) and the per-sample features or None.
        """
        total = total.checked()
        streamed = isinstance(semantic, SampledMaps) and not (torch.is_grad_enabled() and semantic.maps.requires_grad)
        if streamed:
            rendered, per_sample = StreamedRendering.apply(
                total.weights, total.sample_weights, semantic, self.expansion, recompute_samples
            )
        else:
            dense = semantic.dense() if isinstance(semantic, SampledMaps) else semantic
            rendered, per_sample = self.dense_forward(dense, total.weights, total.sample_weights)
        rendered = self.adaptor(rendered)
        if self.adaptor_relu:
            rendered = torch.relu(rendered)
        return rendered, per_sample

    def dense_forward(self, semantic: Tensor, weights: Tensor, sample_weights: Tensor | None) -> tuple[Tensor, Tensor | None]:
        """The reduction over the whole ``[R, S, V, C]`` tensor at once (gradients also reach ``semantic``).

        ``weights``, ``sample_weights``: ``[R, S, V, A]``. Returns ``[R, C]`` and ``[R, S, C]`` (or None).
        """
        num_rays, num_samples, num_views, channels = semantic.shape
        grouped = semantic.reshape(num_rays, num_samples, num_views, self.attention_channels, self.expansion)
        rendered = torch.einsum("rsvae,rsva->rae", grouped, weights).reshape(num_rays, channels)
        per_sample = None
        if sample_weights is not None:
            per_sample = torch.einsum("rsvae,rsva->rsae", grouped, sample_weights)
            per_sample = per_sample.reshape(num_rays, num_samples, channels)
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
