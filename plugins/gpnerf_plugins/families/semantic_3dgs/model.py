"""Per-scene semantic 3D Gaussian splatting: ``model=semantic_3dgs`` (docs/families/semantic_3dgs.md).

3D Gaussian splatting (Kerbl, Kopanas, Leimkuehler, Drettakis, SIGGRAPH 2023; official code
``graphdeco-inria/gaussian-splatting``) fitted on one scene's training frames, with a semantic feature per Gaussian as
Feature 3DGS (Zhou et al., CVPR 2024) and Gaussian Grouping (Ye et al., ECCV 2024) carry one:

- **Start** (``hooks.initialise``, through the public Gaussian strategy ``gpnerf_core.starting_points`` and
  ``rows_from_points``): the scene's sparse points (a capture's structure from motion) or its training frames' depth
  back-projected, at most ``init_points``; colour as the degree-0 harmonic, isotropic scales from the three nearest
  neighbours, opacity 0.1; semantic features uniform as Gaussian Grouping's.
- **Render**: every Gaussian rasterized (``gpnerf_core.rasterize_gaussians``) with its colour from spherical harmonics
  up to the active degree (raised by one every ``sh_degree_every`` steps) seen from the camera, its semantic feature
  composited in the same pass; depth is the composited depth over the accumulated opacity.
- **Semantics**: without a ``+head`` the rendered feature map goes through a 1 x 1 convolution to class scores per
  pixel (Feature 3DGS's decoder, Gaussian Grouping's classifier: label rendering); with a head (``+head=unet``, or
  ``+head=instance`` for Gaussian Grouping's identities) the head decodes it.
- **Train** on whole images (the ``image`` loss set with ``rgb_error=l1``: 0.8 L1 + 0.2 D-SSIM, 3DGS's loss, plus the
  cross-entropy): Adam per parameter with 3DGS's rates and epsilon 1e-15, the centres' rate decayed log-linearly;
  between backward and the optimizer step, density control by the public strategy (``gpnerf_core.DefaultStrategy``:
  3DGS's statistics, densification, pruning and opacity resets on its official schedule; ``model.density=budgeted``:
  ``BudgetedStrategy``, never more than ``max_gaussians``), the schedule's steps scaled to ``train.steps``. What the
  rasterizer reports of each training view reaches the strategy through the step's outputs (``ImageOutput.extras``).

This family keeps only its decoder and its losses; the Gaussians, their start, their render, the colour's degree and
their density control are the public ``GaussianFamily``'s (``gpnerf_core.model.gaussian_family``) on the public strategy
(``gpnerf_core.geometry.gaussians``). Its parameters change size while
it trains (``Capabilities.changes_size``): checkpoints hold the Gaussians they have, and ``eval``, ``render``, ``view``
and ``export`` build it at a checkpoint's size (``hooks.resize_to``).
"""

from __future__ import annotations

import dataclasses

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import (
    ConfigError,
    GaussianFamily,
    GaussianScene,
    GaussianSetup,
    GaussianStart,
    ImageOutput,
    PerceptionHead,
    Prediction,
    SemanticOutput,
    SourceViews,
    StepBatch,
    StepOutput,
    TargetCamera,
    TargetView,
    decode_checked,
    labels_or_head_output,
)


class Semantic3DGS(GaussianFamily):
    """One scene's semantic 3D Gaussians (the module docstring).

    Args:
        head: the perception head decoding the rendered feature map, or None (a 1 x 1 convolution to the classes).
        num_classes: K (0 without a head: colour and depth only).
        feature_dim: channels of each Gaussian's semantic feature (``features``).
        setup: the checked options of ``Semantic3DGSConfig`` (``gpnerf_core.gaussian_setup``).
        feature_stride: pixels per cell of the rendered feature map the decoder reads (1: rendered with the colour).
        feature_field: the configured feature provider (``parts.feature_field()``), or None: with one, each Gaussian
            also carries a feature-field vector (Feature 3DGS), rasterized in the same pass as the colour and the
            semantic feature, distilled against the provider's features (``ImageOutput.features``).
    """

    name = "semantic_3dgs"
    start_channel = "features"
    capabilities = dataclasses.replace(GaussianFamily.capabilities, feature_field=True)

    def __init__(self, *, head: PerceptionHead | None, num_classes: int, feature_dim: int,
                 setup: GaussianSetup, feature_stride: int = 1, feature_field: object = None) -> None:
        decoded = head is not None or int(num_classes) > 0
        super().__init__(channels={"features": feature_dim if decoded else 0}, setup=setup, head=head,
                         feature_field=feature_field)
        self.num_classes = 0 if head is not None else int(num_classes)
        self.feature_stride = int(feature_stride)
        self.classifier = nn.Conv2d(feature_dim, self.num_classes, 1) if head is None and self.num_classes else None

    def begin_decoder(self, start: GaussianStart) -> bool:
        """The decoder begun from a start: the head's weights loaded strictly from ``start.head_state``
        ("features"), or the 1 x 1 classifier set to the identity ("scores": decoded logits equal the rendered
        scores). A ``ConfigError`` naming the keys when the start does not fit the decoder."""
        if start.semantics == "features":
            if self.head is None or start.head_state is None:
                raise ConfigError(f"model=semantic_3dgs: the start from model={start.family} decodes its features with "
                                  "a head; expected +head=<its head> (gpnerf_core.start_overrides)")
            try:
                self.head.load_state_dict(start.head_state, strict=True)
            except RuntimeError as error:
                first = str(error).strip().splitlines()[0]
                raise ConfigError(f"model=semantic_3dgs: the +head does not take the weights of the start's head from "
                                  f"model={start.family} ({first}); expected head.<key> as the start's "
                                  "(gpnerf_core.start_overrides)") from None
            return True
        if start.semantics == "scores":
            if self.classifier is None:
                raise ConfigError(f"model=semantic_3dgs: the start from model={start.family} carries class scores, "
                                  "decoded by the 1 x 1 classifier; expected no +head")
            if self.classifier.in_channels != self.classifier.out_channels:
                raise ConfigError(f"model=semantic_3dgs: the start carries {self.classifier.in_channels} class scores "
                                  f"for {self.classifier.out_channels} classes; expected model.feature_dim="
                                  f"{self.classifier.out_channels}")
            with torch.no_grad():  # the identity: decoded logits equal the rendered scores
                self.classifier.weight.copy_(torch.eye(self.num_classes)[:, :, None, None])
                self.classifier.bias.zero_()
            return True
        return False

    # ---- what the model is ------------------------------------------------------------------------------------------

    @property
    def semantic_output(self) -> SemanticOutput | None:
        return labels_or_head_output(self.head, self.num_classes)

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Each Gaussian parameter in its own group (``model.lr.<group>``: ``means``, ``harmonics``, ...,
        ``features``); the classifier or the head under ``head`` (``model.lr.head``)."""
        groups = self.gaussian_groups()
        decoder = self.head if self.head is not None else self.classifier
        if decoder is not None:
            groups["head"] = list(decoder.parameters())
        return groups

    def check_image_size(self, height: int, width: int) -> None:
        """The feature map's stride divides both sides of the image."""
        if height % self.feature_stride or width % self.feature_stride:
            raise ConfigError(f"model.feature_stride={self.feature_stride}: image size {height}x{width} (HxW); "
                              "expected a stride that divides both sides")

    # ---- rendering --------------------------------------------------------------------------------------------------

    def _decode(self, semantic_map: Tensor, size: tuple[int, int]) -> Tensor:
        """``[1, K, H, W]`` scores of ``[h, w, F]`` rendered features: the head's, or the 1 x 1 convolution's."""
        features = semantic_map.permute(2, 0, 1)[None]
        if self.head is not None:
            return decode_checked(self.head, features, size).logits
        logits = self.classifier(features)
        return logits if tuple(logits.shape[-2:]) == size else F.interpolate(logits, size=size, mode="nearest")

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        return StepOutput(tuple(self._forward_view(view, semantics) for view in batch.views))

    def _forward_view(self, target: TargetView, semantics: bool) -> ImageOutput:
        decodes = semantics and (self.head is not None or self.classifier is not None)
        field = self.feature_source is not None
        output, semantic_map = self.render_view(target.camera,
                                                channels=(decodes and self.feature_stride == 1) or field)
        if field:  # the feature field, rendered in the same pass, decoded to the provider's channels
            output = dataclasses.replace(output, features=self.field_map(semantic_map))
            semantic_map = self.split_channels(semantic_map)["features"]
        if not decodes:
            return output
        if self.feature_stride > 1:  # the feature map on its own grid: a second rasterization
            semantic_map = self.render(target.camera, self.feature_stride, channels=True)[3]
            if field:
                semantic_map = self.split_channels(semantic_map)["features"]
        logits = self._decode(semantic_map, target.camera.image_size)
        if self.head is None:  # label rendering: the per-pixel scores
            return dataclasses.replace(output, scores=logits)
        return dataclasses.replace(output, semantic=semantic_map.permute(2, 0, 1)[None], logits=logits)

    @torch.inference_mode()
    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: object = None) -> Prediction:
        """The view rasterized on a ``stride`` grid (0: every pixel), the features on ``feature_stride``'s;
        ``sources``, ``chunk_rays`` and ``features`` are unused (a per-scene model renders from its own Gaussians in one
        call)."""
        stride = stride or 1
        decodes = self.head is not None or self.classifier is not None
        together = decodes and self.feature_stride == 1
        field = self.feature_source is not None
        rgb, depth, _, semantic_map, _ = self.render(camera, stride, channels=together or field)
        features = None
        if field:  # the feature field on the rendered grid, in the provider's channels
            features = self.field_map(semantic_map)[0]
            semantic_map = self.split_channels(semantic_map)["features"] if together else None
        if decodes and not together:  # the feature map on its own grid (``feature_stride``)
            semantic_map = self.render(camera, self.feature_stride, channels=True)[3]
            if field:
                semantic_map = self.split_channels(semantic_map)["features"]
        logits = self._decode(semantic_map, camera.image_size) if decodes else None
        semantic = semantic_map.permute(2, 0, 1) if semantic_map is not None else None
        return Prediction(rgb=rgb, depth=depth, semantic=semantic, logits=logits, stride=stride, features=features)

    @torch.inference_mode()
    def scene_gaussians(self, sources: SourceViews | None, *, near: float, far: float,
                        features: object = None) -> GaussianScene:
        """The scene's Gaussians, each labelled with the class its own feature is decoded to by the 1 x 1
        convolution (Gaussian Grouping's 3D classification); -1 with a head (it decodes maps, with context) or
        without semantics. With a feature field, each Gaussian's vector in the provider's channels
        (``GaussianScene.feature_field``)."""
        field = self.gaussians
        labels = None
        if self.classifier is not None:
            weight = self.classifier.weight[:, :, 0, 0]
            labels = (field.features @ weight.T + self.classifier.bias).argmax(dim=-1)
        scene = field.as_scene(labels)
        rows = self.field_rows()
        return scene if rows is None else dataclasses.replace(scene, feature_field=rows)
