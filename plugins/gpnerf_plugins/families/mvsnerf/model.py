"""MVSNeRF (Chen et al., ICCV 2021) with a semantic head: ``model=mvsnerf``, GP-NeRF Table 1's "MVSNeRF + Semantic
Head", following the official code ``apchenstu/mvsnerf`` (docs/families/mvsnerf.md).

Per target view:

1. The source views are encoded by the configured ``feature_extractor`` (``mvsnet``: MVSNeRF's FeatureNet, 32 channels
   at 1/4). The first source view is the **reference**.
2. A plane-sweep cost volume in the reference frustum (``gpnerf_core.plane_sweep``): D fronto-parallel planes from near
   to far, uniform in depth; every view's ImageNet-normalised RGB (at the map's resolution) and features are warped onto
   them. The volume has ``3 V + C`` channels: the V views' RGB (the reference's first; 9 + 32 = 41 for MVSNeRF's 3
   views and 32 channels) and the variance of the C-channel features over the views that see each voxel.
3. A 3D U-Net (``networks.CostRegNet``: 41 -> 8, stride-2 levels of 16 / 32 / 64 channels, transposed convs back with
   skip sums) turns it into an 8-channel encoding volume. Its sides must be multiples of 8: the frustum is widened by
   ``model.pad`` cells on each side (MVSNeRF's own padding of the reference frustum) and by the fewest more that get
   there; an image whose 1/4 map has an odd side is refused (``check_image_size``).
4. Each ray sample is mapped to the reference's normalised coordinates (x, y across the image, z from near to far),
   reads the volume trilinearly (zero outside the frustum: a wide-baseline target keeps MVSNeRF's blind spots), and
   each view's colour (border-clamped) and in-image flag: 8 + 4 V features. The coordinates' positional encoding (10
   frequencies), the features and the ray direction rotated into the reference frame go through the modulated MLP
   (``networks.ModulatedMLP``, MVSNeRF's "v0" ``Renderer_ours``), which gives density, colour and, on its trunk, the
   semantic branch's class scores (Linear 128 -> 64, ReLU, Linear 64 -> K).
5. ``alpha = 1 - exp(-sigma)`` with **no** sample interval (MVSNeRF's ``raw2alpha``; its issues #29 and #72): the
   density is per sample, not per metre. Colour, depth and class scores are composited with the same weights (label
   rendering, ``SemanticMode.LABEL_RENDERING``).

With a ``+head`` (``+experiment=baselines/mvsnerf_unet``: GP-NeRF's context-aware decoding on MVSNeRF's field) the
semantic branch outputs ``extractor.semantic_dim`` features in the extractor's semantic-map space instead of K class
scores (Linear 128 -> 64, ReLU, Linear 64 -> C), rendered in the last pass only (the one pass by default) and composited
with the same weights into ``RenderedRays.semantic``; the head decodes them as ``neuray``'s do
(``gpnerf_core.decoded_view_output``: the fused map in training; ``render_whole_view`` with ``decode`` at the semantic
maps' stride on a whole view; ``teacher_logits``: the head on the target image's own semantic map). The teacher needs
semantic maps, which MVSNeRF's FeatureNet (``mvsnet``) has not: that variant uses the configured extractor
(``resunet_fpn``, whose radiance maps are 32 channels at 1/4 like FeatureNet's) for the cost volume too, in place of
FeatureNet; a head with an extractor without semantic maps is refused by the build.

Samples are stratified uniform in depth between near and far (jittered in training from a generator seeded with the
view's ``render_seed``, bin edges in evaluation); ``model.fine_samples`` > 0 adds an importance pass through the same
network (MVSNeRF's runs have none).

Faithful: FeatureNet, the cost volume's channels and count-normalised variance, the 3D U-Net, the NDC lookup, the
per-view colour and flag, the MLP (Kaiming init, multiplicative modulation, skip, density and colour heads), the alpha
without interval, samples uniform in depth, no importance pass, ImageNet-normalised RGB in the volume and raw [0, 1]
colours at the samples, Adam at 5e-4 with a cosine schedule (conf/experiment/baselines/mvsnerf.yaml).

Simplified for a 2-core CPU, and why:

* **Planes 128 -> 48** (``num_planes``): the 3D U-Net's cost grows linearly with D (1.17 GMAC forward at 128
  planes for a 96 x 128 image, 0.44 at 48, by torch's FLOP counter); the volume's depth resolution is coarser.
* **Samples 128 -> 48** (``coarse_samples``): the MLP costs 0.135 M MAC per sample (with a 21-class head), so 128
  samples of 256 rays would be 4.4 GMAC forward per step; the samples are coarser along the ray.
* **Rays 1024 -> 256** per step (``train.rays`` in the baseline experiment), for the same reason.
* **Width**: the MLP keeps MVSNeRF's 128 by default (``width``); the baseline experiment keeps it too.
* **V = 3**, as MVSNeRF (``num_source_views``, ``volume_views``); other counts work (3 channels of RGB and 4 features
  per view), and a target given fewer views than the network was built for gets zeros for the missing ones.
* **Padding**: MVSNeRF pads the 1/4 map of its 512 x 640 DTU images (128 x 160 cells) by ``pad`` = 24 cells per side
  (its default), 15-19 % of the map, and its sides stay multiples of 8. Here ``model.pad`` is a minimum, raised to the
  fewest cells that reach multiples of 8, so any image whose sides are multiples of 8 pixels works (the kit's 32 x 48,
  Replica's and ScanNet's 240 x 320). The family's default is 0 (the cheapest volume); the baseline experiment sets
  [4, 4], about MVSNeRF's share of a 96 x 128 image's 24 x 32 map (the 3D U-Net's cost grows with the area).
* **InPlaceABN -> BatchNorm + LeakyReLU(0.01)** (same function and parameters; in-place saving is a GPU matter).
* **Geometry**: the framework's convention (pixel centres at integers, ``align_corners=False`` on images, the volume
  cells centred on the 1/4 map's cells) instead of MVSNeRF's ``(W - 1)`` normalisation; the variance ignores the
  bilinear edge values of a view whose centre falls outside it (MVSNeRF sums them); points behind a view are outside
  it (MVSNeRF's projection does not test z); with ``pad`` the reference's RGB is zero in the padding (uninitialised
  memory in MVSNeRF's ``torch.empty`` volume) and the reference is counted only inside its image.
* **No per-scene volume**: MVSNeRF's fine-tuning makes the encoding volume a trainable parameter (``RefVolume``) of one
  scene. Here ``finetune`` continues training the whole model on the scene, the volume still computed from the source
  views, as Semantic-Ray's fine-tuning does.
* **Semantic head**: no public code exists for "MVSNeRF + Semantic Head"; the branch is Semantic-NeRF's kind of
  semantic branch, on the trunk before the view-dependent colour branch (our reading of the comparison).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from gpnerf_core import (
    Capabilities,
    LabelsOrHead,
    ConfigError,
    DepthSource,
    FeatureExtractor,
    FeatureMaps,
    PerceptionHead,
    Prediction,
    RayBatch,
    RaySamples,
    ReferenceFrustum,
    RenderedRays,
    SourceViews,
    StepBatch,
    StepOutput,
    TargetCamera,
    TargetView,
    ViewOutput,
    composite,
    compositing_weights,
    decode_checked,
    decoded_view_output,
    density_opacity,
    importance_depths,
    one_pass_preview,
    plane_sweep,
    points_along_rays,
    points_in_views,
    rays_through_pixels,
    render_whole_view,
    stratified_depths,
    SurfaceSampling,
    variance_over_views,
)
from gpnerf_plugins.extractors.mvsnet import imagenet_normalised
from gpnerf_plugins.families.mvsnerf.networks import (
    ENCODING_CHANNELS, LEVELS, CostRegNet, ModulatedMLP, positional_encoding,
)

MAP_STRIDE = 4
"""Stride of the extractor's radiance map (``mvsnet`` and ``resunet_fpn``: 1/4), whose cells are the volume's."""


@dataclass(frozen=True)
class EncodedView:
    """What every ray of one target view reads: the reference frustum and its encoding volume, the views' images.

    Attributes:
        frustum: the reference view's voxel grid (``gpnerf_core.ReferenceFrustum``).
        volume: ``[8, D, h', w']`` encoding volume.
        sources: the (at most ``volume_views``) source views used.
    """

    frustum: ReferenceFrustum
    volume: Tensor
    sources: SourceViews
    maps: FeatureMaps
    """The used views' encoded maps (a depth source sweeps their radiance features)."""


class MVSNeRF(LabelsOrHead):
    """MVSNeRF + semantic head (the module docstring describes it).

    Without a ``head`` the semantic branch gives K class scores per sample, composited per ray: label rendering. With a
    ``head`` it gives features in the extractor's semantic-map space, rendered in the last pass only and decoded by the
    head with GP-NeRF's context-aware decoding (``gpnerf_core.decoded_view_output``), as ``neuray`` with a head.

    Args:
        extractor: the configured feature extractor (its radiance maps, at 1/4 of the image, build the cost volume;
            with a head, its semantic maps are the teacher).
        num_classes: K scores per sample (0: no label rendering) without a head.
        head: the perception head decoding rendered features, or None (label rendering).
        coarse_samples, fine_samples: samples per ray of the pass, and of an importance pass (0: none).
        volume_views: views the network is built for.
        num_planes: D, a multiple of 8.
        inverse_depth: planes and samples uniform in 1/depth.
        pad: cells added on each side of the reference frustum, (rows, columns), at least (``volume_pad``).
        width: MLP width.
        sampling, depth_source: with a depth source (``model.sampler=depth``), one pass on ``fine_samples`` samples
            around its depth of each ray instead of the stratified ones.
    """

    capabilities = Capabilities(teacher=True, preview=True)

    def __init__(self, *, extractor: FeatureExtractor, num_classes: int, coarse_samples: int, fine_samples: int,
                 volume_views: int, num_planes: int, inverse_depth: bool, pad: tuple[int, int], width: int,
                 head: PerceptionHead | None = None, sampling: SurfaceSampling = SurfaceSampling(),
                 depth_source: DepthSource | None = None) -> None:
        super().__init__()
        unit = 2**LEVELS
        if coarse_samples < 2 or fine_samples < 0 or volume_views < 1 or width < 2 or min(pad) < 0:
            raise ConfigError(f"model.coarse_samples={coarse_samples}, fine_samples={fine_samples}, volume_views="
                              f"{volume_views}, width={width}, pad={list(pad)}: expected >= 2, >= 0, >= 1, >= 2 and "
                              "cells >= 0")
        if num_planes < unit or num_planes % unit:
            raise ConfigError(f"model.num_planes={num_planes}: the mvsnerf 3D U-Net halves the depth {LEVELS} times; "
                              f"expected a positive multiple of {unit}")
        self.extractor = extractor
        self.cost_regulariser = CostRegNet(3 * volume_views + extractor.radiance_dim)
        outputs = int(extractor.semantic_dim) if head is not None else int(num_classes)
        self.mlp = ModulatedMLP(ENCODING_CHANNELS + 4 * volume_views, width, outputs)
        self.head = head
        self.num_classes = int(num_classes) if head is None else 0
        self.coarse_samples, self.fine_samples = int(coarse_samples), int(fine_samples)
        self.volume_views, self.num_planes = int(volume_views), int(num_planes)
        self.inverse_depth = bool(inverse_depth)
        self.pad = (int(pad[0]), int(pad[1]))
        self.sampling, self.depth_source = sampling, depth_source

    # ---- what the model is --------------------------------------------------------------------------------------

    def check_image_size(self, height: int, width: int) -> None:
        """The extractor's sizes, and a cost volume whose sides the 3D U-Net can take (``volume_pad``)."""
        self.extractor.check_image_size(height, width)
        if height % MAP_STRIDE or width % MAP_STRIDE:
            raise ConfigError(f"image size {height}x{width} (HxW): mvsnerf's cost volume has one cell per "
                              f"{MAP_STRIDE}x{MAP_STRIDE} pixels; expected multiples of {MAP_STRIDE}")
        self.volume_pad(height // MAP_STRIDE, width // MAP_STRIDE, f"image size {height}x{width} (HxW)")

    def volume_pad(self, rows: int, cols: int, what: str) -> tuple[int, int]:
        """Cells added on each side of a ``rows`` x ``cols`` frustum, (rows, columns): at least ``model.pad``, and the
        fewest more that make both sides multiples of 8. A ConfigError naming ``what`` for an odd side (no even padding
        makes it a multiple of 8)."""
        unit = 2**LEVELS
        needed = [(-(side + 2 * pad)) % unit for side, pad in zip((rows, cols), self.pad)]
        if any(need % 2 for need in needed):
            raise ConfigError(
                f"{what}: mvsnerf's cost volume is {rows}x{cols} cells (1/{MAP_STRIDE} of the image), and its 3D U-Net "
                f"needs sides that are multiples of {unit} after padding them evenly on both sides, which an odd side "
                f"cannot reach; expected image sides that are multiples of {2 * MAP_STRIDE} pixels")
        return self.pad[0] + needed[0] // 2, self.pad[1] + needed[1] // 2

    def encode(self, images: Tensor) -> FeatureMaps:
        return self.extractor(images)

    # ---- the volume -----------------------------------------------------------------------------------------------

    def _encoded(self, sources: SourceViews, maps: FeatureMaps, near: float, far: float) -> EncodedView:
        """The reference frustum and its encoding volume from the (first ``volume_views``) source views."""
        count = min(sources.num_views, self.volume_views)
        used = SourceViews(sources.rgb[:count], sources.intrinsics[:count], sources.c2w[:count])
        features = maps.radiance[:count]
        rows, cols = (int(side) for side in features.shape[-2:])
        pad = self.volume_pad(rows, cols, f"feature map {rows}x{cols}")
        frustum = ReferenceFrustum(used.intrinsics[0], used.c2w[0], used.image_size, (rows, cols), float(near),
                                   float(far), self.num_planes, self.inverse_depth, pad)
        sweep = plane_sweep(frustum, used.intrinsics, used.c2w)
        colours = F.interpolate(imagenet_normalised(used.rgb), size=(rows, cols), mode="bilinear", align_corners=False)
        colours = sweep.warp(colours).flatten(0, 1)  # [3 V, D, h', w']
        missing = colours.new_zeros(3 * (self.volume_views - count), *colours.shape[1:])
        cost = torch.cat([colours, missing, variance_over_views(sweep.warp(features), sweep.inside)], dim=0)
        return EncodedView(frustum, self.cost_regulariser(cost[None])[0], used, FeatureMaps(features, None))

    # ---- one pass -------------------------------------------------------------------------------------------------

    def _pass(self, rays: RayBatch, samples: RaySamples, view: EncodedView, semantics: bool,
              sample_semantics: bool = False) -> RenderedRays:
        """Render ``rays`` at ``samples``; with ``semantics`` the semantic branch's outputs too: class scores composited
        into ``logits`` (label rendering), or with a head features composited into ``semantic`` (and per sample into
        ``sample_semantic`` with ``sample_semantics``)."""
        num_rays, num_samples = samples.depths.shape
        points = samples.points.reshape(-1, 3)
        coordinates = view.frustum.coordinates(points)  # [N, 3]
        grid, inside = points_in_views(points, view.sources.intrinsics, view.sources.c2w, view.sources.image_size)
        colours = F.grid_sample(view.sources.rgb, grid[:, :, None].to(view.sources.rgb.dtype), mode="bilinear",
                                padding_mode="border", align_corners=False)[..., 0]  # [V, 3, N]
        per_view = torch.cat([colours, inside[:, None].to(colours.dtype)], dim=1).permute(2, 0, 1)  # [N, V, 4]
        per_view = F.pad(per_view, (0, 0, 0, self.volume_views - per_view.shape[1])).flatten(1)
        feature = torch.cat([view.frustum.sample(view.volume, coordinates), per_view], dim=-1)
        rotation = view.frustum.c2w[:3, :3]
        direction = F.normalize(rays.directions, dim=-1) @ rotation  # the reference camera's frame
        direction = direction[:, None].expand(-1, num_samples, -1).reshape(-1, 3)
        density, colour, trunk = self.mlp(positional_encoding(coordinates), feature, direction)
        weights = compositing_weights(density_opacity(density.reshape(num_rays, num_samples)))  # no interval
        rendered = RenderedRays(rgb=composite(weights, colour.view(num_rays, num_samples, 3)), weights=weights,
                                depth=(weights * samples.depths).sum(-1), samples=samples)
        if not semantics or self.mlp.semantic is None:
            return rendered
        outputs = self.mlp.scores(trunk).view(num_rays, num_samples, -1)
        if self.head is None:
            return replace(rendered, logits=composite(weights, outputs))
        return replace(rendered, semantic=composite(weights, outputs),
                       sample_semantic=outputs if sample_semantics else None)

    def preview_sampling(self, depth_source: DepthSource, samples: int) -> contextlib.AbstractContextManager[bool]:
        """One pass of the network on ``samples`` samples around ``depth_source``'s depth (the model's own, when built
        with one) while entered; the configured sampling is restored on exit."""
        return one_pass_preview(self, depth_source, samples)

    def _render(self, rays: RayBatch, view: EncodedView, semantics: bool, generator: torch.Generator | None,
                sample_semantics: bool = False) -> tuple[RenderedRays, RenderedRays | None]:
        """The pass and (with fine samples) the importance pass through the same network; with a head only the last
        pass renders semantic features (GP-NeRF's), without one both render class scores. With a depth source, one
        pass on ``fine_samples`` samples around its depth."""
        if self.depth_source is not None:
            depths = self.depth_source.sample_depths(
                rays, view.sources, view.maps, self.fine_samples, spread=self.sampling.spread,
                uncertainty=self.sampling.uncertainty, perturb=generator is not None, generator=generator)
            return self._pass(rays, points_along_rays(rays, depths), view, semantics, sample_semantics), None
        depths = stratified_depths(rays, self.coarse_samples, inverse=self.inverse_depth, generator=generator)
        coarse_semantics = semantics and (self.head is None or not self.fine_samples)
        coarse = self._pass(rays, points_along_rays(rays, depths), view, coarse_semantics, sample_semantics)
        if not self.fine_samples:
            return coarse, None
        extra = importance_depths(depths, coarse.weights, self.fine_samples, deterministic=generator is None,
                                  generator=generator)
        fine = self._pass(rays, points_along_rays(rays, torch.cat([depths, extra], -1)), view, semantics,
                          sample_semantics)
        return coarse, fine

    # ---- the contract ---------------------------------------------------------------------------------------------

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        return StepOutput(tuple(self._forward_view(view, semantics, sample_semantics) for view in batch.views))

    def _forward_view(self, target: TargetView, semantics: bool, sample_semantics: bool = False) -> ViewOutput:
        if target.sources is None:
            raise ConfigError("mvsnerf renders from source views; the target view has none")
        camera = target.camera
        rays = rays_through_pixels(target.pixels, camera.intrinsics, camera.c2w, camera.near, camera.far)
        generator = None
        if self.training:
            generator = torch.Generator(device=target.pixels.device).manual_seed(target.render_seed)
        maps = self.encode(target.sources.rgb[: self.volume_views])  # the views the network reads
        view = self._encoded(target.sources, maps, camera.near, camera.far)
        coarse, fine = self._render(rays, view, semantics, generator, sample_semantics)
        if self.head is None or not semantics:
            return ViewOutput(coarse=coarse, fine=fine)
        return decoded_view_output(target, coarse, fine, self.encode(target.image[None]).semantic, self.head)

    @torch.inference_mode()
    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: FeatureMaps | None = None) -> Prediction:
        if sources is None:
            raise ConfigError("mvsnerf renders from source views; none were given")
        maps = features if features is not None else self.encode(sources.rgb)
        view = self._encoded(sources, maps, camera.near, camera.far)
        semantics = self.mlp.semantic is not None
        decode = None
        if self.head is not None:  # the rendered map at the semantic maps' stride, decoded with its context
            stride = stride or max(1, camera.height // int(maps.semantic.shape[-2]))
            decode = lambda semantic_map, size: decode_checked(self.head, semantic_map, size).logits  # noqa: E731

        def render(rays: RayBatch) -> RenderedRays:
            coarse, fine = self._render(rays, view, semantics, None)
            return fine if fine is not None else coarse

        return render_whole_view(camera, render, stride=stride, chunk_rays=chunk_rays, decode=decode)
