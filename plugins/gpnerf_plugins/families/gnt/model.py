"""The ``gnt`` model family: GNT's transformers over source views with GP-NeRF's semantic field and a perception head.

``GeneralizableNeRF.forward`` is the training pass of GP-NeRF's Fig. 2, top-down: encode the source views (and the
target view, the teacher), render the chosen rays with the field and ray aggregators, render the semantic field
from their attention, write the rendered features into the teacher map (the fused map) and decode it with the
perception head. ``predict`` renders whole views for evaluation and rendering. The extractor, the two aggregators and
the head are components of their own kinds (``feature_extractor=``, ``field_aggregator=``, ``ray_aggregator=``,
``+head=``), built through ``ModelParts``; without a head (or with ``model.semantic_field.enabled=false``) it is GNT
alone.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
from typing import Any, Mapping

import torch
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint as activation_checkpoint

from gpnerf_core import (
    Capabilities,
    ConfigError,
    FamilyHooks,
    FeatureExtractor,
    FeatureMaps,
    FieldAggregator,
    FieldBlockOutput,
    HeadOutput,
    ImportedWeights,
    ModelFamily,
    PerceptionHead,
    Prediction,
    Predicts,
    Projector,
    RayAggregator,
    RayBatch,
    RayBlockOutput,
    RaySamples,
    RenderedRays,
    SemanticMode,
    SemanticOutput,
    SourceViews,
    StepBatch,
    StepOutput,
    TargetCamera,
    TargetView,
    ViewOutput,
    decode_checked,
    DepthSource,
    decoded_view_output,
    importance_depths,
    one_pass_preview,
    pixel_grid,
    points_along_rays,
    quiet_rng,
    rays_through_pixels,
    sampling_layout,
    stage,
    stratified_inverse_depths,
    surface_depths,
    SurfaceSampling,
)
from gpnerf_plugins.families.gnt.semantic_field import AttentionSums, SemanticFieldRenderer
from gpnerf_plugins.families.gnt.weights import read_gnt_checkpoint


@functools.lru_cache(maxsize=None)
def compiled_block_pair(backend: str, num_blocks: int):
    """``torch.compile`` d ``GeneralizableNeRF._block_pair``. Each block index (its own modules) and each pass's
    shapes (coarse, fine, a last chunk) is a graph of its own, so dynamo's per-function recompile limit (8) would
    leave the later blocks eager: it is raised to 6 graphs per block. One wrapper per backend, so switching back and
    forth reuses the graphs."""
    import torch._dynamo

    torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 6 * num_blocks)
    return torch.compile(GeneralizableNeRF._block_pair, backend=backend)


class GNTHooks(FamilyHooks):
    """GNT's compiled path, and its outputs named by the stage that made them."""

    def output_owners(self, names: Mapping[str, str]) -> dict[str, str]:
        rendering = f"field aggregator {names.get('field_aggregator')!r} / ray aggregator {names.get('ray_aggregator')!r}"
        return {"colour": rendering, "depth": rendering,
                "semantic map": f"semantic field (the attention of the {rendering})", "logits": f"head {names.get('head')!r}"}

    def use_compiled(self, backend: str | None) -> None:
        self.family.compile_with(backend)


class GeneralizableNeRF(ModelFamily):
    """Extractor -> projector -> field aggregator <-> ray aggregator -> semantic field -> fused map -> head.

    Args:
        extractor, field, ray: the stages; the ray aggregator must have as many blocks as the field aggregator.
        head: perception head on the semantic map, or None (GNT alone).
        semantic: the semantic field renderer, or None (GNT alone).
        coarse_samples: stratified samples per ray; fine_samples: samples of the fine pass beside (``uniform``) or
            instead of (``depth``) the coarse ones (0 = one pass).
        sampling: where the fine samples go (``SurfaceSampling``).
        depth_source: with ``sampling.sampler == "depth"``, each ray's cheap depth from the source views (one pass on
            ``fine_samples`` samples, no coarse pass); None: from the coarse pass.
        detach_source_semantics: stop rendered-feature losses from training the extractor through the
            source views (the released code does, REFERENCE §3 (ii)).
        fuse_rendered: the head decodes the fused map in training (paper); False decodes the teacher map
            alone (released code).
        checkpoint_blocks: recompute each transformer block pair in the backward pass instead of keeping its
            activations (activation checkpointing; less memory, more compute), and sample the source semantic
            maps again in backward instead of keeping them.
        channels_last_maps: hold the detached source semantic maps channels-last while they are sampled
            (``geometry.projection.sampling_layout``: the same values, faster ``grid_sample``).
        compile_backend: ``torch.compile`` the block pairs and the semantic attention sums with this backend
            (None: eager). Compiled on first use, again for each new shape (coarse and fine passes, last chunk).
    """

    capabilities = Capabilities(teacher=True, preview=True, compiled=True, foreign_weights=True, hooks=GNTHooks,
                                feature_field=True)

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
        detach_source_semantics: bool,
        sampling: SurfaceSampling = SurfaceSampling(),
        depth_source: DepthSource | None = None,
        fuse_rendered: bool,
        checkpoint_blocks: bool,
        channels_last_maps: bool = True,
        compile_backend: str | None = None,
        feature_field: Any = None,
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
        if sampling.sampler == "depth" and fine_samples == 0:
            raise ConfigError("model.sampler=depth places the fine pass's samples around the coarse depth; expected "
                              "model.fine_samples >= 1 (0 = one pass, nothing to place)")
        self.extractor = extractor
        self.field = field
        self.ray = ray
        self.head = head
        self.semantic = semantic
        self.coarse_samples = coarse_samples
        self.fine_samples = fine_samples
        if depth_source is not None and sampling.sampler != "depth":
            raise ConfigError(f"depth_source {type(depth_source).__name__} places the samples of model.sampler=depth; "
                              f"expected model.sampler=depth with it (model.sampler is {sampling.sampler!r})")
        self.sampling = sampling
        self.depth_source = depth_source
        self.detach_source_semantics = detach_source_semantics
        self.fuse_rendered = fuse_rendered
        self.checkpoint_blocks = checkpoint_blocks
        self.channels_last_maps = channels_last_maps
        self.projector = Projector()
        self.compile_with(compile_backend)
        self.feature_source = feature_field  # a plain object: the provider is no submodule (never trained or saved)
        self.feature_projection: nn.Linear | None = None
        if feature_field is not None:
            if semantic is None:
                raise ConfigError(f"+feature_provider={feature_field.name}: model=gnt renders its feature field from "
                                  "its semantic-embedding field, which is off; expected model.semantic_field.enabled="
                                  "true and a feature extractor with semantic maps")
            with quiet_rng():  # the global RNG as without a field (dropout and the rest draw the same)
                self.feature_projection = nn.Linear(semantic.semantic_dim, int(feature_field.channels))

    @property
    def renders_field(self) -> bool:
        """It renders a feature field (``+feature_provider``): the semantic embedding per ray, projected to the
        provider's channels (``feature_projection``)."""
        return self.feature_projection is not None

    def with_field(self, coarse: RenderedRays, fine: RenderedRays | None
                   ) -> tuple[RenderedRays, RenderedRays | None]:
        """The passes with the last one's ``features``: its semantic embedding ``[R, C_sem]`` projected to the
        provider's ``[R, C]``; unchanged without a feature field."""
        if self.feature_projection is None:
            return coarse, fine
        last = fine if fine is not None else coarse
        done = dataclasses.replace(last, features=self.feature_projection(last.semantic))
        return (coarse, done) if fine is not None else (done, None)

    @property
    def has_semantics(self) -> bool:
        return self.semantic is not None and self.head is not None

    @property
    def semantic_output(self) -> SemanticOutput | None:
        """Decoded by the head on the rendered map (GP-NeRF's context-aware path); None for GNT alone."""
        if not self.has_semantics:
            return None
        predicts = Predicts(self.head.predicts)
        slots = getattr(self.head, "slots", None) if predicts is Predicts.INSTANCES else None
        return SemanticOutput(predicts, SemanticMode.DECODED, int(self.head.num_outputs), slots)

    def check_image_size(self, height: int, width: int) -> None:
        """The extractor's limits (its strides)."""
        self.extractor.check_image_size(height, width)

    def read_foreign(self, checkpoint: Mapping[str, Any]) -> ImportedWeights | None:
        """An official GNT checkpoint (``net_coarse`` + ``feature_net``): each stage maps its share, and the semantic
        adaptor GP-NeRF's code adds to ``net_coarse``."""
        return read_gnt_checkpoint(self, checkpoint)

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Parameters by learning-rate group: ``feature_extractor``, ``transformer``, ``head``."""
        transformer = list(self.field.parameters()) + list(self.ray.parameters())
        if self.semantic is not None:
            transformer += list(self.semantic.parameters())
        if self.feature_projection is not None:
            transformer += list(self.feature_projection.parameters())
        groups = {"feature_extractor": list(self.extractor.parameters()), "transformer": transformer}
        if self.head is not None:
            groups["head"] = list(self.head.parameters())
        return groups

    # ---- the training pass (GP-NeRF Fig. 2, top-down) ----------------------------------------------------------

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        """Render the chosen rays of every target view of ``batch`` and decode its fused map.

        Args:
            batch: the target views of this process's step.
            semantics: render semantic features and run the head (the loss set needs them).
            sample_semantics: also return per-sample semantic features (the D.G loss).

        Returns:
            One ``ViewOutput`` per target view. In training mode the samples are jittered with the generator
            seeded by each view's ``render_seed``; in eval mode they are deterministic.
        """
        if semantics and not self.has_semantics:
            raise ConfigError("semantic outputs were requested but the model has no head or semantic field")
        return StepOutput(tuple(self.forward_view(view, semantics, sample_semantics) for view in batch.views))

    def forward_view(self, view: TargetView, semantics: bool, sample_semantics: bool) -> ViewOutput:
        """The training pass of one target view (see ``forward``)."""
        sources = view.sources
        # 1. Multi-scale features of the source views; the target's own semantic map is the teacher.
        with stage("encode sources"):
            source_maps = self.encode(sources.rgb)
            if self.detach_source_semantics and source_maps.semantic is not None:
                # No loss trains the extractor through the sources' semantic maps: drop their graph now, so backward
                # never runs the FPN over the sources and its activations are freed before the transformers run.
                semantic_maps = self._for_sampling(source_maps.semantic.detach(), int(view.pixels.shape[0]))
                source_maps = FeatureMaps(radiance=source_maps.radiance, semantic=semantic_maps)
        teacher = None
        if semantics:
            with stage("encode target (teacher)"):
                teacher = self.encode(view.image[None]).semantic
        # 2. Rays through the chosen pixels: radiance and semantic fields, coarse then fine.
        camera = view.camera
        rays = rays_through_pixels(view.pixels, camera.intrinsics, camera.c2w, camera.near, camera.far)
        generator = None
        if self.training:
            generator = torch.Generator(device=view.pixels.device).manual_seed(view.render_seed)
        coarse, fine = self.render_rays(
            rays,
            sources,
            source_maps,
            randomized=self.training,
            with_semantic=semantics or self.renders_field,
            with_sample_semantic=sample_semantics,
            generator=generator,
        )
        coarse, fine = self.with_field(coarse, fine)
        if not semantics:
            return ViewOutput(coarse=coarse, fine=fine)
        # 3. The fused map (rendered features replace the teacher's in the cells the rays hit), decoded by the
        # context-aware perception head on the whole map.
        with stage("head"):
            return decoded_view_output(view, coarse, fine, teacher, self.head, fuse=self.fuse_rendered)

    # ---- whole views (evaluation, rendering) ---------------------------------------------------------------------

    @torch.inference_mode()
    def predict(
        self,
        camera: TargetCamera,
        sources: SourceViews,
        *,
        stride: int,
        chunk_rays: int,
        features: FeatureMaps | None = None,
    ) -> Prediction:
        """Render a whole target view and decode the rendered semantic map.

        Args:
            camera: the target camera.
            sources: its source views.
            stride: render every ``stride``-th pixel (cell centres); 0 = the semantic map's stride, so the head
                sees a complete map.
            chunk_rays: rays rendered at once (bounds memory).
            features: the sources' encoded maps when the caller keeps them (``feature_cache.SourceFeatureCache``);
                None encodes them here.

        Source features are computed once and reused for every chunk; per-sample semantic features are never
        materialised.
        """
        with stage("encode sources"):
            if features is None:
                features = self.encode(sources.rgb)
            stride = stride or self.semantic_stride(features, camera.height)
            height, width = camera.image_size
            if height % stride or width % stride:
                raise ConfigError(f"image size {height}x{width} is not divisible by eval.render_stride={stride}")
            if features.semantic is not None and not features.semantic.requires_grad:
                maps = self._for_sampling(features.semantic, (height // stride) * (width // stride))
                features = FeatureMaps(radiance=features.radiance, semantic=maps)
        pixels = pixel_grid(height, width, stride, device=camera.c2w.device)
        rays = rays_through_pixels(pixels, camera.intrinsics, camera.c2w, camera.near, camera.far)
        rgb, depth, semantic, field = [], [], [], []
        for start in range(0, rays.num_rays, chunk_rays):
            coarse, fine = self.with_field(*self.render_rays(
                rays.chunk(start, start + chunk_rays),
                sources,
                features,
                randomized=False,
                with_semantic=self.has_semantics or self.renders_field,
            ))
            last = fine if fine is not None else coarse
            rgb.append(last.rgb)
            depth.append(last.depth)
            if last.semantic is not None and self.has_semantics:
                semantic.append(last.semantic)
            if last.features is not None:
                field.append(last.features)
        h, w = height // stride, width // stride
        semantic_map = torch.cat(semantic).T.reshape(-1, h, w) if semantic else None
        with stage("head"):
            logits = self.decode(semantic_map[None], camera.image_size).logits if semantic_map is not None else None
        return Prediction(
            rgb=torch.cat(rgb).reshape(h, w, 3),
            depth=torch.cat(depth).reshape(h, w),
            semantic=semantic_map,
            logits=logits,
            stride=stride,
            features=torch.cat(field).T.reshape(-1, h, w) if field else None,
        )

    @torch.inference_mode()
    def teacher_logits(self, image: Tensor) -> Tensor:
        """The 2D-only reference: the head on the target image's own semantic map, ``[3, H, W]`` -> ``[1, K, H, W]``."""
        return self.decode(self.encode(image[None]).semantic, tuple(image.shape[-2:])).logits

    @staticmethod
    def semantic_stride(features: FeatureMaps, height: int) -> int:
        """Pixels per cell of the semantic map (1 without one)."""
        if features.semantic is None:
            return 1
        return max(1, height // int(features.semantic.shape[-2]))

    # ---- the stages ------------------------------------------------------------------------------------------------

    def encode(self, images: Tensor) -> FeatureMaps:
        """Feature maps of ``[N, 3, H, W]`` images."""
        return self.extractor(images)

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
        """Coarse pass, then (with fine samples) a fine pass on coarse + importance samples (``uniform``) or on samples
        around the coarse depth (``depth``).

        Semantics are rendered in the last pass only. ``randomized`` jitters the samples (training).
        """
        if self.samples_from_sweep:
            around = self.depth_source.sample_depths(
                rays, sources, features, self.fine_samples, spread=self.sampling.spread,
                uncertainty=self.sampling.uncertainty, perturb=randomized, generator=generator,
            )
            only = self.render_pass(rays, points_along_rays(rays, around), sources, features,
                                    with_semantic=with_semantic, with_sample_semantic=with_sample_semantic)
            return only, None
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
        if self.sampling.sampler == "depth":
            around, _ = surface_depths(
                rays, coarse_samples.depths, coarse.weights, self.fine_samples, spread=self.sampling.spread,
                uncertainty=self.sampling.uncertainty, perturb=randomized, generator=generator,
            )
            fine_samples = points_along_rays(rays, around)
        else:
            extra = importance_depths(
                coarse_samples.depths, coarse.weights, self.fine_samples, deterministic=not randomized,
                generator=generator,
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

    @property
    def samples_from_sweep(self) -> bool:
        """``model.sampler=depth`` with a ``depth_source``: one pass on ``fine_samples`` samples, no coarse pass."""
        return self.sampling.sampler == "depth" and self.depth_source is not None

    def preview_sampling(self, depth_source: DepthSource, samples: int) -> contextlib.AbstractContextManager[bool]:
        """One pass on ``samples`` samples around the depth of ``depth_source`` (or of the model's own depth source)
        while entered; the configured sampling is restored on exit, whatever happens."""
        return one_pass_preview(self, depth_source, samples)

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
        """One pass of the transformers over given samples; semantics from their attention when asked."""
        with_semantic = with_semantic and self.semantic is not None and features.semantic is not None
        if with_semantic and self.detach_source_semantics:
            features = FeatureMaps(radiance=features.radiance, semantic=features.semantic.detach())
        with stage("projection"):
            projected = self.projector(samples, rays.origins, sources, features, with_semantic=with_semantic)
        recompute = self.checkpoint_blocks and torch.is_grad_enabled()
        attention = AttentionSums(with_samples=with_sample_semantic) if with_semantic else None
        last = None
        with stage("transformers"):
            tokens, context = self.field.begin(projected, samples, rays)
        for index in range(self.field.num_blocks):
            with stage("transformers"):
                if recompute:
                    field_out, last = activation_checkpoint(
                        self._pair, self, index, tokens, context, use_reentrant=False
                    )
                else:
                    field_out, last = self._pair(self, index, tokens, context)
                tokens = last.tokens
            if attention is not None:
                with stage("semantic field"):
                    self.semantic.add_block(attention, field_out.view_attention, last.ray_attention)
        with stage("transformers"):
            readout = self.ray.readout(tokens, last)
            depth = (readout.weights * samples.depths).sum(dim=-1)
        semantic = sample_semantic = None
        if attention is not None:
            with stage("semantic field"):
                semantic, sample_semantic = self.semantic.render(
                    projected.semantic, attention, recompute_samples=self.checkpoint_blocks
                )
        return RenderedRays(
            rgb=readout.rgb,
            weights=readout.weights,
            depth=depth,
            samples=samples,
            semantic=semantic,
            sample_semantic=sample_semantic,
        )

    def compile_with(self, backend: str | None) -> None:
        """Run the block pairs and the semantic attention sums ``torch.compile`` d with ``backend`` (None: eager;
        ``hooks.use_compiled``)."""
        self.compile_backend = backend
        # Unbound (called with self), so a copy of the module never runs the original's blocks.
        self._pair = type(self)._block_pair if backend is None else compiled_block_pair(backend, self.field.num_blocks)
        if self.semantic is not None:
            self.semantic.compile_sums(backend)

    def _for_sampling(self, maps: Tensor, rays: int) -> Tensor:
        """``maps`` channels-last (``sampling_layout``) when each view will be sampled at more points (``rays`` x all
        samples per ray) than the maps hold pixels: below that the copy costs more than it saves (measured:
        ``docs/benchmarks.md``, channels-last)."""
        per_ray = self.fine_samples + (0 if self.sampling.sampler == "depth" else self.coarse_samples)
        samples = rays * (per_ray if self.samples_from_sweep else max(self.coarse_samples, per_ray))
        if self.channels_last_maps and samples >= maps.shape[-2] * maps.shape[-1]:
            return sampling_layout(maps)
        return maps

    def _block_pair(self, index: int, tokens: Tensor, context: object) -> tuple[FieldBlockOutput, RayBlockOutput]:
        """Field block ``index`` then ray block ``index`` (GNT interleaves them)."""
        field_out = self.field.block(index, tokens, context)
        return field_out, self.ray.block(index, field_out.tokens)

    def decode(self, semantic_map: Tensor, output_size: tuple[int, int]) -> HeadOutput:
        """Run the perception head on a ``[N, C, h, w]`` semantic map; its output is checked against the contract."""
        if self.head is None:
            raise ConfigError("this model has no perception head: add one with +head=<name>")
        return decode_checked(self.head, semantic_map, output_size)
