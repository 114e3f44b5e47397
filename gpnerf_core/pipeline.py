"""The generalizable NeRF assembled from its four stages, a semantic field and a perception head."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from gpnerf_core.errors import ConfigError
from gpnerf_core.geometry import (
    Projector,
    importance_depths,
    pixel_grid,
    points_along_rays,
    rays_through_pixels,
    stratified_inverse_depths,
)
from gpnerf_core.interfaces import FeatureExtractor, FieldAggregator, PerceptionHead, RayAggregator
from gpnerf_core.semantic_field import SemanticFieldRenderer
from gpnerf_core.types import FeatureMaps, HeadOutput, RayBatch, RaySamples, RenderedRays, SourceViews


@dataclass(frozen=True)
class RenderedImage:
    """A target view rendered on a stride grid.

    Attributes:
        rgb: ``[h, w, 3]`` (unclamped); depth: ``[h, w]`` metres.
        semantic: ``[C, h, w]`` rendered semantic map, or None.
        stride: pixels of the full image per rendered cell.
    """

    rgb: Tensor
    depth: Tensor
    semantic: Tensor | None
    stride: int


class GeneralizableNeRF(nn.Module):
    """Extractor -> projector -> field aggregator <-> ray aggregator -> semantic field -> head.

    Args:
        extractor, field, ray: the stages; the ray aggregator must have as many blocks as the field aggregator.
        head: perception head on the semantic map, or None (GNT alone).
        semantic: the semantic field renderer, or None (GNT alone).
        coarse_samples: stratified samples per ray; fine_samples: importance samples added in the fine pass
            (0 = one pass).
        detach_source_semantics: stop rendered-feature losses from training the extractor through the
            source views (the released code does, REFERENCE §3 (ii)).
    """

    def __init__(
        self,
        *,
        extractor: FeatureExtractor,
        field: FieldAggregator,
        ray: RayAggregator,
        head: PerceptionHead | None,
        semantic: SemanticFieldRenderer | None,
        coarse_samples: int,
        fine_samples: int,
        detach_source_semantics: bool = True,
    ) -> None:
        super().__init__()
        if field.num_blocks != ray.num_blocks:
            raise ConfigError(
                f"field aggregator has {field.num_blocks} blocks but ray aggregator has {ray.num_blocks}; they interleave"
            )
        if coarse_samples < 2:
            raise ConfigError(f"model.coarse_samples must be >= 2, got {coarse_samples}")
        if fine_samples < 0:
            raise ConfigError(f"model.fine_samples must be >= 0, got {fine_samples}")
        self.extractor = extractor
        self.field = field
        self.ray = ray
        self.head = head
        self.semantic = semantic
        self.coarse_samples = coarse_samples
        self.fine_samples = fine_samples
        self.detach_source_semantics = detach_source_semantics
        self.projector = Projector()

    @property
    def has_semantics(self) -> bool:
        return self.semantic is not None and self.head is not None

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Parameters by learning-rate group: ``feature_extractor``, ``transformer``, ``head``."""
        transformer = list(self.field.parameters()) + list(self.ray.parameters())
        if self.semantic is not None:
            transformer += list(self.semantic.parameters())
        groups = {"feature_extractor": list(self.extractor.parameters()), "transformer": transformer}
        if self.head is not None:
            groups["head"] = list(self.head.parameters())
        return groups

    def encode(self, images: Tensor) -> FeatureMaps:
        """Feature maps of ``[N, 3, H, W]`` images."""
        return self.extractor(images)

    def render_pass(
        self,
        rays: RayBatch,
        samples: RaySamples,
        sources: SourceViews,
        features: FeatureMaps,
        *,
        with_semantic: bool,
        with_sample_semantic: bool = False,
    ) -> RenderedRays:
        """One pass of the transformers over given samples."""
        with_semantic = with_semantic and self.semantic is not None and features.semantic is not None
        if with_semantic and self.detach_source_semantics:
            features = FeatureMaps(radiance=features.radiance, semantic=features.semantic.detach())
        projected = self.projector(samples, rays.origins, sources, features, with_semantic=with_semantic)
        tokens, context = self.field.begin(projected, samples, rays)
        view_attention, ray_attention = [], []
        last = None
        for index in range(self.field.num_blocks):
            field_out = self.field.block(index, tokens, context)
            last = self.ray.block(index, field_out.tokens)
            tokens = last.tokens
            if with_semantic:
                view_attention.append(field_out.view_attention)
                ray_attention.append(last.ray_attention)
        readout = self.ray.readout(tokens, last)
        depth = (readout.weights * samples.depths).sum(dim=-1)
        semantic = sample_semantic = None
        if with_semantic:
            semantic, sample_semantic = self.semantic(
                projected.semantic, view_attention, ray_attention, with_samples=with_sample_semantic
            )
        return RenderedRays(
            rgb=readout.rgb,
            weights=readout.weights,
            depth=depth,
            samples=samples,
            semantic=semantic,
            sample_semantic=sample_semantic,
        )

    def render_rays(
        self,
        rays: RayBatch,
        sources: SourceViews,
        features: FeatureMaps,
        *,
        randomized: bool,
        with_semantic: bool,
        with_sample_semantic: bool = False,
        generator: torch.Generator | None = None,
    ) -> tuple[RenderedRays, RenderedRays | None]:
        """Coarse pass, then (with fine samples) a fine pass on coarse + importance samples.

        Semantics are rendered in the last pass only. ``randomized`` jitters the samples (training).
        """
        depths = stratified_inverse_depths(rays, self.coarse_samples, perturb=randomized, generator=generator)
        coarse_samples = points_along_rays(rays, depths)
        one_pass = self.fine_samples == 0
        coarse = self.render_pass(
            rays,
            coarse_samples,
            sources,
            features,
            with_semantic=with_semantic and one_pass,
            with_sample_semantic=with_sample_semantic and one_pass,
        )
        if one_pass:
            return coarse, None
        extra = importance_depths(
            coarse_samples.depths, coarse.weights, self.fine_samples, deterministic=not randomized, generator=generator
        )
        fine_samples = points_along_rays(rays, torch.cat([coarse_samples.depths, extra], dim=-1))
        fine = self.render_pass(
            rays,
            fine_samples,
            sources,
            features,
            with_semantic=with_semantic,
            with_sample_semantic=with_sample_semantic,
        )
        return coarse, fine

    def decode(self, semantic_map: Tensor, output_size: tuple[int, int]) -> HeadOutput:
        """Run the perception head on a ``[N, C, h, w]`` semantic map."""
        if self.head is None:
            raise ConfigError("this model has no perception head: add one with +head=<name>")
        return self.head(semantic_map, output_size)

    @torch.inference_mode()
    def render_image(
        self,
        *,
        intrinsics: Tensor,
        c2w: Tensor,
        height: int,
        width: int,
        near: float,
        far: float,
        sources: SourceViews,
        features: FeatureMaps,
        stride: int,
        chunk_rays: int,
    ) -> RenderedImage:
        """Render a whole target view on the ``stride`` grid in chunks of ``chunk_rays`` rays.

        Source features are computed once by the caller and reused for every chunk; per-sample semantic
        features are never materialised here.
        """
        if height % stride or width % stride:
            raise ConfigError(f"image size {height}x{width} is not divisible by eval.render_stride={stride}")
        pixels = pixel_grid(height, width, stride, device=c2w.device)
        rays = rays_through_pixels(pixels, intrinsics, c2w, near, far)
        rgb, depth, semantic = [], [], []
        for start in range(0, rays.num_rays, chunk_rays):
            chunk = rays.chunk(start, start + chunk_rays)
            coarse, fine = self.render_rays(
                chunk, sources, features, randomized=False, with_semantic=self.has_semantics
            )
            last = fine if fine is not None else coarse
            rgb.append(last.rgb)
            depth.append(last.depth)
            if last.semantic is not None:
                semantic.append(last.semantic)
        h, w = height // stride, width // stride
        semantic_map = torch.cat(semantic).T.reshape(-1, h, w) if semantic else None
        return RenderedImage(
            rgb=torch.cat(rgb).reshape(h, w, 3),
            depth=torch.cat(depth).reshape(h, w),
            semantic=semantic_map,
            stride=stride,
        )
