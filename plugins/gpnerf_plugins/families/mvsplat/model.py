"""MVSplat (Chen et al., ECCV 2024, official code ``donydchen/mvsplat``) with semantics: ``model=mvsplat``, the first
family that rasterizes instead of marching rays (docs/families/mvsplat.md).

From the V source views, once per source set (``encode_sources``, kept by ``render``, ``view`` and ``export``):

1. The configured ``feature_extractor`` encodes each view; its 1/4 radiance map, projected to ``feature_dim`` channels,
   is MVSplat's "CNN feature" (``project``).
2. The multi-view Transformer (``transformer.MultiViewTransformer``) lets every view attend to itself and to the others
   in (shifted) windows.
3. Per view, a plane-sweep cost volume of feature correlations with the other views over ``depth_candidates`` depths
   uniform in inverse depth (``gpnerf_core.plane_sweep``), refined by a 2D U-Net; depth by soft-argmin; upsampled to
   the image and refined by a second U-Net; a head gives each pixel's Gaussian (``depth.DepthPredictor``).
4. One Gaussian per source pixel (``adapter.pixel_gaussians``): centre at its depth, opacity from the refinement
   (MVSplat's ``map_pdf_to_opacity`` is the identity with its released settings), scale, rotation, spherical-harmonic
   colour.

Per target view, the Gaussians are rasterized (``gpnerf_core.rasterize_gaussians``, any backend): colour from the
harmonics seen from the target, depth, and the semantics, both ways:

* **label rendering** (no ``+head``): each Gaussian also carries K class scores from the same head, composited per
  pixel like the colour (``+experiment=baselines/mvsplat``);
* **decoded** (``+head=unet``): each Gaussian carries the extractor's semantic feature at its source pixel, rasterized
  into a map at the semantic maps' resolution that the head decodes with its image context, GP-NeRF's decoding on a
  Gaussian field (``+experiment=baselines/mvsplat_unet``); in training the map is rendered whole, so it is the head's
  input as it is (every cell is rendered: nothing of the teacher is fused in), and the S.D loss compares it with the
  target image's own map at every pixel.

With ``+feature_provider`` (a feature field, docs/features.md): each Gaussian also carries the provider's feature of
its source view at its source pixel (the provider's map lifted bilinearly to every pixel,
``gpnerf_core.lift_to_pixels``; nothing is trained), rasterized into ``Prediction.features`` and given as
``GaussianScene.feature_field``.

Training renders whole target images (``TrainingBatch.IMAGES``: one ``ImageOutput`` per target view): MVSplat's loss is
on images (MSE + 0.05 LPIPS; LPIPS needs weights that cannot be downloaded here, so the ``image`` loss set takes SSIM
in its place).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import (
    Capabilities,
    ConfigError,
    FeatureExtractor,
    GaussianScene,
    Gaussians,
    ImageOutput,
    LabelsOrHead,
    PerceptionHead,
    Prediction,
    SourceEncoding,
    SourceViews,
    StepBatch,
    StepOutput,
    TargetCamera,
    TargetView,
    TrainingBatch,
    decode_checked,
    lift_to_pixels,
    rasterize_gaussians,
    rotate_harmonics,
    sh_coefficients,
    strided_camera,
)
from gpnerf_plugins.families.mvsplat.adapter import GEOMETRY_CHANNELS, PixelGaussians, pixel_gaussians
from gpnerf_plugins.families.mvsplat.checkpoints import MVSplatHooks
from gpnerf_plugins.families.mvsplat.depth import DepthPredictor
from gpnerf_plugins.families.mvsplat.transformer import MultiViewTransformer

MAP_STRIDE = 4
"""Stride of the extractor's radiance map, the cost volume's cells."""


@dataclass(frozen=True)
class RenderedImage:
    """One view rasterized on a ``stride`` grid: colour ``[h, w, 3]``, depth ``[h, w]`` (metres, the composited
    depth over the accumulated opacity; 0 where nothing is), accumulated opacity ``[h, w]``, class scores ``[h, w, K]``
    or None, the semantic map ``[1, C, h, w]`` or None, and the feature field ``[1, C_f, h, w]`` or None."""

    rgb: Tensor
    depth: Tensor
    alpha: Tensor
    scores: Tensor | None
    semantic: Tensor | None = None
    features: Tensor | None = None


class MVSplat(LabelsOrHead):
    """MVSplat with semantics (the module docstring).

    Args:
        extractor: the configured feature extractor (its 1/4 radiance maps; with a head, its semantic maps and the
            teacher).
        head: the perception head decoding the rasterized semantic map, or None (label rendering).
        num_classes: K class scores per Gaussian without a head (0: colour and depth only).
        feature_dim, transformer_layers, attention_splits: the multi-view Transformer.
        depth_candidates, cost_unet_dim, depth_unet_dim, unet_levels: the depth predictor.
        sh_degree, scale_min, scale_max: the Gaussian adapter.
        background: colour where no Gaussian covers a pixel.
        rasterizer: the rasterizer backend (``gpnerf_core.rasterize_gaussians``).
        feature_field: the configured feature provider (``parts.feature_field()``), or None: with one, each Gaussian
            carries the provider's feature at its source pixel (``PixelGaussians.field``).
    """

    capabilities = Capabilities(trains_on=TrainingBatch.IMAGES, source_encoding=SourceEncoding.SOURCE_SET, gaussians=True,
                                teacher=True, hooks=MVSplatHooks, feature_field=True)

    def __init__(self, *, extractor: FeatureExtractor, head: PerceptionHead | None, num_classes: int, feature_dim: int,
                 transformer_layers: int, attention_splits: int, depth_candidates: int, cost_unet_dim: int,
                 depth_unet_dim: int, unet_levels: int, sh_degree: int, scale_min: float, scale_max: float,
                 background: float, rasterizer: str, feature_field: object = None) -> None:
        super().__init__()
        self.feature_source = feature_field  # a plain object: the provider is no submodule (never trained or saved)
        self.extractor, self.head = extractor, head
        self.num_classes = int(num_classes) if head is None else 0
        self.sh_degree, self.scale_min, self.scale_max = int(sh_degree), float(scale_min), float(scale_max)
        self.background, self.rasterizer = float(background), str(rasterizer)
        self.attention_splits, self.unet_levels = int(attention_splits), int(unet_levels)
        raw = GEOMETRY_CHANNELS + 3 * sh_coefficients(self.sh_degree) + self.num_classes
        self.project = nn.Conv2d(extractor.radiance_dim, feature_dim, 1)
        self.transformer = MultiViewTransformer(feature_dim, transformer_layers, attention_splits)
        self.depth = DepthPredictor(feature_dim=feature_dim, candidates=depth_candidates, cost_dim=cost_unet_dim,
                                    depth_dim=depth_unet_dim, levels=unet_levels, raw_channels=raw,
                                    upscale=MAP_STRIDE)

    # ---- what the model is ------------------------------------------------------------------------------------------

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """The extractor under ``feature_extractor``, the head under ``head``, MVSplat's own networks
        under its own group ``mvsplat`` (``model.lr.mvsplat``)."""
        groups = super().parameter_groups()
        groups["mvsplat"] = groups.pop("transformer")
        return groups

    def check_image_size(self, height: int, width: int) -> None:
        """The extractor's sizes; a 1/4 map whose sides the attention windows and the U-Net can take."""
        self.extractor.check_image_size(height, width)
        unit = MAP_STRIDE * self.attention_splits
        if height % unit or width % unit:
            raise ConfigError(f"image size {height}x{width} (HxW): mvsplat's attention cuts the 1/{MAP_STRIDE} feature "
                              f"map into {self.attention_splits}x{self.attention_splits} windows (model.attention_"
                              f"splits); expected sides that are multiples of {unit} pixels")

    # ---- the Gaussians of a source set ------------------------------------------------------------------------------

    def encode_sources(self, sources: SourceViews, *, near: float, far: float) -> PixelGaussians:
        """One Gaussian per pixel of every source view (the module docstring, steps 1-4); ``near`` and ``far`` bound
        the depth candidates, metres."""
        if sources.num_views < 1:
            raise ConfigError("mvsplat predicts Gaussians from source views: expected at least 1 (2 to match them "
                              "against each other; model.num_source_views)")
        maps = self.extractor(sources.rgb)
        cnn = self.project(maps.radiance)
        depth = self.depth(self.transformer(cnn), cnn, sources, near, far)
        semantic, semantic_stride = None, 0
        if self.head is not None:
            semantic_stride = sources.image_size[0] // int(maps.semantic.shape[-2])
            semantic = F.interpolate(maps.semantic, size=sources.image_size, mode="bilinear", align_corners=False)
        gaussians = pixel_gaussians(depth.raw, depth.depth, depth.opacity, depth.confidence, sources,
                                    sh_degree=self.sh_degree, scale_min=self.scale_min, scale_max=self.scale_max,
                                    semantic=semantic, semantic_stride=semantic_stride, extras=self.num_classes)
        if self.feature_source is None or self.training:  # nothing trains the lifted field: left out of training
            return gaussians
        return dataclasses.replace(gaussians, field=self.lifted_field(sources))

    def lifted_field(self, sources: SourceViews) -> Tensor:
        """``[V H W, C]`` the feature provider's map of each source view lifted to every pixel (bilinear, the map's
        cells covering the image evenly: ``gpnerf_core.lift_to_pixels``), view-major then row-major as the Gaussians
        (one per source pixel); the maps of a dataset's frames are read through the provider cache. Not trained."""
        with torch.no_grad():
            maps = self.feature_source.maps(sources.scene, sources.frames, sources.rgb)  # [V, C, h, w]
            lifted = lift_to_pixels(maps, sources.image_size)
        return lifted.permute(0, 2, 3, 1).reshape(-1, int(maps.shape[1]))

    # ---- rasterizing ------------------------------------------------------------------------------------------------

    def _rasterize(self, gaussians: PixelGaussians, features: Tensor, camera: TargetCamera, stride: int,
                   background: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        intrinsics, height, width = strided_camera(camera, stride)
        out = rasterize_gaussians(
            Gaussians(gaussians.means, gaussians.scales, gaussians.rotations, gaussians.opacities, features),
            intrinsics=intrinsics, c2w=camera.c2w, height=height, width=width, background=background,
            backend=self.rasterizer)
        return out.features, out.depth, out.alpha

    def render_image(self, gaussians: PixelGaussians, camera: TargetCamera, stride: int, *, scores: bool,
                     semantic: bool = False, field: bool = False) -> RenderedImage:
        """Colour, depth, and (``scores``, label rendering) class scores, (``semantic``) the semantic map and
        (``field``) the feature field of ``camera`` on a ``stride`` grid, in one rasterization."""
        parts = [gaussians.colours(camera.c2w[:3, 3])]
        if scores:
            parts.append(gaussians.scores)
        if semantic:
            parts.append(gaussians.semantic)
        if field:
            parts.append(gaussians.field)
        features = torch.cat(parts, dim=-1) if len(parts) > 1 else parts[0]
        background = torch.zeros(features.shape[1], dtype=features.dtype, device=features.device)
        background[:3] = self.background
        image, depth, alpha = self._rasterize(gaussians, features, camera, stride, background)
        expected = torch.where(alpha > 1e-6, depth / alpha.clamp_min(1e-6), torch.zeros_like(depth))
        classes = gaussians.scores.shape[1] if scores else 0
        width = gaussians.semantic.shape[1] if semantic else 0
        return RenderedImage(rgb=image[..., :3], depth=expected, alpha=alpha,
                             scores=image[..., 3:3 + classes] if scores else None,
                             semantic=(image[..., 3 + classes:3 + classes + width].permute(2, 0, 1)[None] if semantic
                                       else None),
                             features=image[..., 3 + classes + width:].permute(2, 0, 1)[None] if field else None)

    def render_semantic(self, gaussians: PixelGaussians, camera: TargetCamera, stride: int) -> Tensor:
        """``[1, C, h, w]`` the Gaussians' semantic features rasterized on a ``stride`` grid (what the head decodes)."""
        image, _, _ = self._rasterize(gaussians, gaussians.semantic, camera, stride)
        return image.permute(2, 0, 1)[None]

    # ---- the contract -----------------------------------------------------------------------------------------------

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        return StepOutput(tuple(self._forward_view(view, semantics) for view in batch.views))

    def _forward_view(self, target: TargetView, semantics: bool) -> ImageOutput:
        """The whole target rendered: colour, depth, opacity, and the class scores (label rendering) or the semantic
        map with the head's logits and the target's own map (decoded)."""
        if target.sources is None:
            raise ConfigError("mvsplat renders from source views; the target view has none")
        camera = target.camera
        gaussians = self.encode_sources(target.sources, near=camera.near, far=camera.far)
        labels = semantics and self.head is None and self.num_classes > 0
        image = self.render_image(gaussians, camera, 1, scores=labels)
        scores = image.scores.permute(2, 0, 1)[None] if labels else None
        if self.head is None or not semantics:
            return ImageOutput(rgb=image.rgb, depth=image.depth, alpha=image.alpha, scores=scores)
        teacher = self.extractor(target.image[None]).semantic  # [1, C, h, w], not detached: the loss set decides
        stride = camera.height // int(teacher.shape[-2])
        semantic_map = self.render_semantic(gaussians, camera, stride)
        logits = decode_checked(self.head, semantic_map, camera.image_size).logits
        return ImageOutput(rgb=image.rgb, depth=image.depth, alpha=image.alpha, semantic=semantic_map,
                           teacher_map=teacher, logits=logits)

    @torch.inference_mode()
    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: PixelGaussians | None = None) -> Prediction:
        """The view rasterized on a ``stride`` grid (0: the semantic maps' stride with a head, else every pixel);
        ``features``: the source set's Gaussians when the caller keeps them (``encode_sources``). ``chunk_rays`` is
        unused: a rasterized view is one call."""
        if sources is None and features is None:
            raise ConfigError("mvsplat renders from source views; none were given")
        gaussians = features if features is not None else self.encode_sources(sources, near=camera.near,
                                                                                far=camera.far)
        labels = self.head is None and self.num_classes > 0
        stride = stride or (gaussians.semantic_stride if self.head is not None else 1)
        field = gaussians.field is not None
        image = self.render_image(gaussians, camera, stride, scores=labels, semantic=self.head is not None, field=field)
        semantic = logits = None
        if self.head is not None:
            logits = decode_checked(self.head, image.semantic, camera.image_size).logits
            semantic = image.semantic[0]
        elif labels:
            logits = image.scores.permute(2, 0, 1)[None]
            if stride > 1:
                logits = F.interpolate(logits, size=camera.image_size, mode="nearest")
        features = image.features[0] if field else None
        return Prediction(rgb=image.rgb, depth=image.depth, semantic=semantic, logits=logits, stride=stride,
                          features=features)

    @torch.inference_mode()
    def scene_gaussians(self, sources: SourceViews | None, *, near: float, far: float,
                        features: PixelGaussians | None = None) -> GaussianScene:
        """The Gaussians of ``sources`` in the world frame, each labelled with the class the model predicts at its
        own source pixel: its class scores' argmax (label rendering), or the head's class in the source view
        rendered from the set (decoded: the head needs the image context, so a label is a pixel's of a decoded view);
        -1 without semantics. The scene's ``features`` column: each Gaussian's semantic feature (with a head) or its class scores (label
        rendering), None without semantics; ``feature_field``: the provider's feature at its source pixel, or None."""
        if sources is None and features is None:
            raise ConfigError("mvsplat predicts Gaussians from source views; none were given")
        gaussians = features if features is not None else self.encode_sources(sources, near=near, far=far)
        views, height, width = gaussians.depth.shape
        labels = torch.full((gaussians.count,), -1, dtype=torch.long, device=gaussians.means.device)
        if self.head is None and self.num_classes:
            labels = gaussians.scores.argmax(dim=-1)
        elif self.head is not None and sources is not None:
            per_view = []
            for view in range(views):
                camera = TargetCamera(sources.intrinsics[view], sources.c2w[view], height, width, near, far)
                logits = self.predict(camera, None, stride=0, chunk_rays=0, features=gaussians).logits
                per_view.append(logits[0].argmax(dim=0).reshape(-1))
            labels = torch.cat(per_view)
        harmonics = rotate_harmonics(gaussians.harmonics, gaussians.source_rotations, gaussians.view_of)
        own = gaussians.semantic if self.head is not None else gaussians.scores  # what the decoder reads
        return GaussianScene(means=gaussians.means, scales=gaussians.scales, rotations=gaussians.rotations,
                             opacities=gaussians.opacities, harmonics=harmonics, labels=labels, features=own,
                             feature_field=gaussians.field)
