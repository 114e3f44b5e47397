"""The ``neuray`` and ``semantic_ray`` families: NeuRay's occlusion-aware generalizable renderer with label rendering.

Semantic-Ray (Liu et al., CVPR 2023; ``liuff19/Semantic-Ray``) is NeuRay (Liu et al., CVPR 2022;
``liuyuan-pal/NeuRay``) plus a Cross-Reprojection Attention (CRA) on each sample's per-view features and a per-view
semantic classifier whose scores are blended with the colour weights and volume-rendered (label rendering). "NeuRay +
Semantic Head" of GP-NeRF's Table 1 is the same network without the CRA (Semantic-Ray's ``use_ptrans: false``).
What carries over from the official code (docs/families/neuray.md):

- visibility from source-view depth: ``DepthInitNet`` (image, normalised inverse depth and its reprojection
  consistency), the visibility encoder, and per pass a decoder of a two-component mixture of logistics read at each
  projection, giving each source ray's visibility ``vis`` and hit probability ``hit`` over the target sample's
  interval; their embedding q weights the mean/variance pooling (``w0 = sigmoid(MLP(q)) * w``, not renormalised) and
  enters BaseFC;
- IBRNet's aggregation: direction embedding, BaseFC, visibility re-weighting, density from the pooled statistics
  through one ray-attention layer (query masks, as the official layers), colour blended by a softmax over views;
- the semantic head: ``[Linear(g'), the density MLP's first layer (g'), u_i]`` -> per-view scores, blended by the
  colour weights; nothing detached;
- ``alpha = 1 - exp(-sigma)`` without the sample interval (the method's convention);
- coarse samples uniform in inverse depth, never jittered; the fine pass renders only its own samples, drawn from
  the coarse weights (detached) in normalised inverse depth (randomly in training, at the bins' centres in
  evaluation); separate visibility decoders and aggregation networks for the two passes;
- losses (``+experiment=baselines/semantic_ray``): 0.75 x the per-ray channel sum of squared colour error per pass
  (2.25 x this framework's per-channel mean) and 0.25 x the cross-entropy per pass, no depth loss.

Changed for this framework and two CPU cores, each a deviation to keep in mind when reading its numbers:

- image features come from the configured ``feature_extractor`` (the CPU-sized ResNet-34 U-Net's 32 radiance
  channels at 1/4, IBRNet's encoder) in place of Semantic-Ray's lighter ResNet-UNet of the same width;
- ``DepthInitNet``'s encoder has one residual block per stage down to 1/8 (NeuRay: 1/2/6 blocks down to 1/16);
- 4 source views (``scale=cpu``; Semantic-Ray 8), 24 + 24 samples (64 + 64), 256 rays per step (1024);
- K class scores, without Semantic-Ray's extra "invalid" slot: the framework's ignore label gets no loss, and an
  untrained slot's argmax would only drop pixels from the metric (a quirk of the official metric);
- no "ray mask" on the colour loss (the official loss skips rays with at most 8 samples seen by more than 2 views);
  no weight decay (1e-5 there); the learning-rate schedule is the experiment's (a constant 1e-3 over a short run;
  officially 1e-3 x 0.2 every 5k steps down to 5e-5);
- trained from scratch: NeuRay's pretrained generalizable depth model, from which Semantic-Ray starts, is not
  available offline;
- fine-tuning (``finetune``) continues training the whole network on one scene, as Semantic-Ray's fine-tuning does
  (not NeuRay's per-view free visibility maps).

Source-view depth is an input at training and test time (as officially: THU-SI/Semantic-Ray issue #5); where a
frame has no depth (0, e.g. ``dataset=capture``) its inverse-depth and consistency channels are zero and G comes from
the image alone, which is no longer NeuRay's visibility (docs/families/neuray.md).
"""

from __future__ import annotations

import contextlib
from dataclasses import replace

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import (
    Capabilities,
    LabelsOrHead,
    ConfigError,
    DepthSource,
    FeatureMaps,
    PerceptionHead,
    Prediction,
    RayBatch,
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
    points_along_rays,
    project_points,
    rays_through_pixels,
    render_whole_view,
    stratified_inverse_depths,
    SurfaceSampling,
    world_to_camera,
)
from gpnerf_plugins.families.neuray.aggregator import NeuRayAggregator
from gpnerf_plugins.families.neuray.visibility import (
    DepthInitNet,
    VisibilityDecoder,
    VisibilityEncoder,
    normalized_inverse_depth,
)


class PassNetwork(nn.Module):
    """The networks of one pass (coarse or fine): a visibility decoder and an aggregation network."""

    def __init__(self, feature_dim: int, visibility_dim: int, semantic_outputs: int, cross_reprojection: bool) -> None:
        super().__init__()
        self.decoder = VisibilityDecoder(visibility_dim)
        self.aggregator = NeuRayAggregator(feature_dim, visibility_dim, semantic_outputs, cross_reprojection)


class VisibilityAwareRenderer(LabelsOrHead):
    """NeuRay's renderer with Semantic-Ray's semantic head (and CRA when ``cross_reprojection``).

    Without a ``head`` the semantic head's per-view outputs are K class scores, blended and volume-rendered: label
    rendering, as the official methods. With a ``head`` they are features in the extractor's semantic-map space,
    rendered per ray and decoded by the head with GP-NeRF's context-aware decoding (the fused map in training, the
    rendered map on a whole view; ``gpnerf_core.decoded_view_output``): GP-NeRF's decoding on this family's field.
    The semantic outputs are then rendered in the last pass only, as GP-NeRF's.

    Args:
        extractor: the configured feature extractor (its radiance maps are the image features; with a head, its
            semantic maps are the teacher).
        num_classes: K class scores per sample (0: colour and depth only) without a head.
        head: the perception head decoding rendered features, or None (label rendering).
        coarse_samples, fine_samples: samples of the two passes (the fine pass renders only its own).
        visibility_dim: channels of the visibility maps G.
        cross_reprojection: Semantic-Ray's Cross-Reprojection Attention.
    """

    capabilities = Capabilities(teacher=True, preview=True)

    def __init__(self, *, extractor: nn.Module, num_classes: int, head: PerceptionHead | None, coarse_samples: int,
                 fine_samples: int, visibility_dim: int, cross_reprojection: bool,
                 sampling: SurfaceSampling = SurfaceSampling(), depth_source: DepthSource | None = None) -> None:
        super().__init__()
        if coarse_samples < 2 or fine_samples < 0 or visibility_dim < 2 or visibility_dim % 2:
            raise ConfigError(f"model.coarse_samples={coarse_samples}, model.fine_samples={fine_samples}, "
                              f"model.visibility_dim={visibility_dim}: expected >= 2, >= 0 and an even number >= 2")
        self.extractor = extractor
        self.depth_init = DepthInitNet(visibility_dim)
        self.visibility_encoder = VisibilityEncoder(extractor.radiance_dim + visibility_dim, visibility_dim)
        feature_dim = extractor.radiance_dim
        outputs = int(extractor.semantic_dim) if head is not None else int(num_classes)
        # With a depth source the coarse network renders the one pass (on fine_samples samples around the depth).
        two_passes = bool(fine_samples) and depth_source is None
        coarse_outputs = 0 if head is not None and two_passes else outputs
        self.coarse = PassNetwork(feature_dim, visibility_dim, coarse_outputs, cross_reprojection)
        self.fine = PassNetwork(feature_dim, visibility_dim, outputs, cross_reprojection) if two_passes else None
        self.sampling, self.depth_source = sampling, depth_source
        self.head = head
        self.coarse_samples, self.fine_samples = int(coarse_samples), int(fine_samples)
        self.num_classes = int(num_classes) if head is None else 0

    # ---- what the model is ------------------------------------------------------------------------------------------

    def check_image_size(self, height: int, width: int) -> None:
        self.extractor.check_image_size(height, width)
        if height % 4 or width % 4:
            raise ConfigError(f"image size {height}x{width}: the visibility maps are at 1/4 resolution; expected a "
                              "height and width divisible by 4")

    def encode(self, images: Tensor) -> FeatureMaps:
        return self.extractor(images)

    # ---- rendering ---------------------------------------------------------------------------------------------------

    def visibility_maps(self, sources: SourceViews, image_features: Tensor, near: float, far: float) -> Tensor:
        """G ``[V, visibility_dim, h, w]`` of the source views (from their images, depths and image features)."""
        return self.visibility_encoder(image_features, self.depth_init(sources, near, far))

    def _pass(self, net: PassNetwork, rays: RayBatch, depths: Tensor, sources: SourceViews, maps: Tensor,
              semantics: bool, sample_semantics: bool = False) -> RenderedRays:
        """Render ``rays`` at ``depths`` ``[R, S]`` (ascending); ``maps`` ``[V, C + G, h, w]`` (image features and
        visibility maps, sampled together; the colour at its own resolution, on the same grid)."""
        samples = points_along_rays(rays, depths)
        num_rays, num_samples, _ = samples.points.shape
        views, _, height, width = sources.rgb.shape
        pixels, z = project_points(samples.points.reshape(-1, 3), sources.intrinsics, sources.c2w)  # [V, N, .]
        visible = ((z > 1e-4) & (pixels[..., 0] >= -0.5) & (pixels[..., 0] <= width - 0.5)
                   & (pixels[..., 1] >= -0.5) & (pixels[..., 1] <= height - 0.5))
        scale = torch.tensor([2.0 / width, 2.0 / height], dtype=pixels.dtype, device=pixels.device)
        grid = ((pixels + 0.5) * scale - 1.0)[:, :, None, :]
        sampled = torch.cat([F.grid_sample(sources.rgb, grid, align_corners=False),
                             F.grid_sample(maps, grid, align_corners=False)], 1)[..., 0]  # [V, 3 + C + G, N]
        sampled = sampled.permute(2, 0, 1).reshape(num_rays, num_samples, views, -1)
        visible = visible.T.reshape(num_rays, num_samples, views)
        sampled = sampled * visible[..., None]
        visibility_dim = net.decoder.mean[0].in_features
        rgb_features, g = sampled[..., :-visibility_dim], sampled[..., -visibility_dim:]
        t_low, t_high = self._source_intervals(rays, depths, sources)
        vis, hit = net.decoder(g, t_low, t_high)
        q = net.aggregator.embed_probabilities(g, hit, vis)
        directions = self._directions(rays, samples.points, sources)
        density, colour, outputs = net.aggregator(rgb_features, directions, visible, q, semantics)
        weights = compositing_weights(density_opacity(density))  # alpha = 1 - exp(-sigma), no interval
        rendered = RenderedRays(rgb=composite(weights, colour), weights=weights,
                                depth=(weights * samples.depths).sum(-1), samples=samples)
        if outputs is None:
            return rendered
        if self.head is None:
            return replace(rendered, logits=composite(weights, outputs))
        return replace(rendered, semantic=composite(weights, outputs),
                       sample_semantic=outputs if sample_semantics else None)

    @staticmethod
    def _source_intervals(rays: RayBatch, depths: Tensor, sources: SourceViews) -> tuple[Tensor, Tensor]:
        """Each sample's interval on the target ray (between the midpoints to its neighbours) as normalised inverse
        depths ``[R, S, V]`` along each source view's ray through its projection (low end, high end)."""
        middle = (depths[:, 1:] + depths[:, :-1]) / 2
        low = torch.cat([2 * depths[:, :1] - middle[:, :1], middle], -1).clamp_min(1e-4)
        high = torch.cat([middle, 2 * depths[:, -1:] - middle[:, -1:]], -1)
        w2c = world_to_camera(sources.c2w)  # [V, 4, 4]
        z_origin = rays.origins @ w2c[:, 2, :3].T + w2c[:, 2, 3]  # [R, V]: camera z is linear along the ray
        z_step = rays.directions @ w2c[:, 2, :3].T  # [R, V]
        z_low = z_origin[:, None] + low[..., None] * z_step[:, None]
        z_high = z_origin[:, None] + high[..., None] * z_step[:, None]
        near, far = rays.near[:, None, None], rays.far[:, None, None]
        t_a, t_b = (normalized_inverse_depth(z, near, far) for z in (z_low, z_high))
        return torch.minimum(t_a, t_b), torch.maximum(t_a, t_b)

    @staticmethod
    def _directions(rays: RayBatch, points: Tensor, sources: SourceViews) -> Tensor:
        """NeuRay's ``[R, S, V, 4]`` direction features: unit direction to the source camera minus the one to the
        target camera (not renormalised, unlike IBRNet's), and their dot product."""
        to_target = F.normalize(rays.origins[:, None, :] - points, dim=-1)  # [R, S, 3]
        to_source = F.normalize(sources.c2w[:, :3, 3][None, None] - points[:, :, None], dim=-1)  # [R, S, V, 3]
        dot = (to_source * to_target[:, :, None]).sum(-1, keepdim=True)
        return torch.cat([to_source - to_target[:, :, None], dot], -1)

    def render_rays(self, rays: RayBatch, sources: SourceViews, maps: Tensor, semantics: bool,
                    generator: torch.Generator | None, sample_semantics: bool = False,
                    last_pass_semantics: bool = False,
                    features: FeatureMaps | None = None) -> tuple[RenderedRays, RenderedRays | None]:
        """The coarse pass and (with fine samples) the fine pass; ``generator`` None renders deterministically.

        ``last_pass_semantics``: the coarse pass renders no semantics where a fine pass follows (a whole view's
        prediction reads the last pass only; training's cross-entropy reads both). With a depth source
        (``model.sampler=depth``) one pass on ``fine_samples`` samples around its depth from the sources' encoded
        ``features``."""
        if self.depth_source is not None:
            depths = self.depth_source.sample_depths(
                rays, sources, features, self.fine_samples, spread=self.sampling.spread,
                uncertainty=self.sampling.uncertainty, perturb=generator is not None, generator=generator)
            return self._pass(self.last_pass, rays, depths, sources, maps, semantics, sample_semantics), None
        depths = stratified_inverse_depths(rays, self.coarse_samples, perturb=False)
        coarse_semantics = semantics and not (last_pass_semantics and self.fine is not None)
        coarse = self._pass(self.coarse, rays, depths, sources, maps, coarse_semantics, sample_semantics)
        if self.fine is None:
            return coarse, None
        near, far = rays.near[:, None], rays.far[:, None]
        t = normalized_inverse_depth(depths, near, far)
        t_fine = importance_depths(t, coarse.weights.detach(), self.fine_samples, deterministic=generator is None,
                                   generator=generator)
        fine_depths = torch.sort(1.0 / (1.0 / near + t_fine * (1.0 / far - 1.0 / near)), dim=-1).values
        return coarse, self._pass(self.fine, rays, fine_depths, sources, maps, semantics, sample_semantics)

    @property
    def last_pass(self) -> nn.Module:
        """The network of the last pass: the one pass around a depth source's depth (the coarse network of a model
        built with one; the fine network, trained on samples near the surface, in a two-pass model's preview)."""
        return self.fine if self.fine is not None else self.coarse

    def preview_sampling(self, depth_source: DepthSource, samples: int) -> contextlib.AbstractContextManager[bool]:
        """One pass of the last pass's network on ``samples`` samples around ``depth_source``'s depth (the model's own,
        when built with one) while entered; the configured sampling is restored on exit."""
        return one_pass_preview(self, depth_source, samples)

    def _stacked(self, sources: SourceViews, features: FeatureMaps, camera: TargetCamera) -> Tensor:
        """The sources' image features with their visibility maps ``[V, C + G, h, w]`` (sampled together)."""
        visibility = self.visibility_maps(sources, features.radiance, camera.near, camera.far)
        return torch.cat([features.radiance, visibility], 1)

    # ---- the contract ----------------------------------------------------------------------------------------------

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        return StepOutput(tuple(self._forward_view(view, semantics, sample_semantics) for view in batch.views))

    def _forward_view(self, view: TargetView, semantics: bool, sample_semantics: bool) -> ViewOutput:
        camera = view.camera
        rays = rays_through_pixels(view.pixels, camera.intrinsics, camera.c2w, camera.near, camera.far)
        generator = torch.Generator(device=view.pixels.device).manual_seed(view.render_seed) if self.training else None
        if view.sources is None:
            raise ConfigError(f"model {type(self).__name__} renders from source views; the batch has none")
        maps = self.encode(view.sources.rgb)
        coarse, fine = self.render_rays(rays, view.sources, self._stacked(view.sources, maps, camera), semantics,
                                        generator, sample_semantics, features=maps)
        if self.head is None or not semantics:
            return ViewOutput(coarse=coarse, fine=fine)
        return decoded_view_output(view, coarse, fine, self.encode(view.image[None]).semantic, self.head)

    @torch.inference_mode()
    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: FeatureMaps | None = None) -> Prediction:
        if sources is None:
            raise ConfigError(f"model {type(self).__name__} renders from source views; none were given")
        features = features if features is not None else self.encode(sources.rgb)
        maps = self._stacked(sources, features, camera)
        decode = None
        if self.head is not None:  # the rendered map at the semantic maps' stride, decoded with its context
            stride = stride or max(1, camera.height // int(features.semantic.shape[-2]))
            decode = lambda semantic_map, size: decode_checked(self.head, semantic_map, size).logits  # noqa: E731

        def render(rays: RayBatch) -> RenderedRays:
            coarse, fine = self.render_rays(rays, sources, maps, self.semantic_output is not None, None,
                                            last_pass_semantics=True, features=features)
            return fine if fine is not None else coarse

        return render_whole_view(camera, render, stride=stride, chunk_rays=chunk_rays, decode=decode)
