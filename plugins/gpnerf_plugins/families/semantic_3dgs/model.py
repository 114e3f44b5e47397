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

This family keeps only its schedule (the colour's degree), its decoder and its losses; the Gaussians, their start and
their density control are the public strategy's (``gpnerf_core.geometry.gaussians``). Its parameters change size while
it trains (``Capabilities.changes_size``): checkpoints hold the Gaussians they have, and ``eval``, ``render``, ``view``
and ``export`` build it at a checkpoint's size (``hooks.resize_to``).
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import (
    Capabilities,
    ConfigError,
    DefaultStrategy,
    FamilyHooks,
    GaussianParameters,
    GaussianScene,
    GroupOptions,
    ImageOutput,
    ModelFamily,
    NonFiniteError,
    PerceptionHead,
    Prediction,
    Scene,
    SemanticOutput,
    SourceViews,
    StepBatch,
    StepOutput,
    TargetCamera,
    TargetView,
    TrainingBatch,
    TrainingCallback,
    TrainingPhase,
    TrainingState,
    ViewInfo,
    colour_to_dc,
    decode_checked,
    labels_or_head_output,
    neighbour_scales,
    rasterize_gaussians,
    rows_from_points,
    scaled_step,
    scene_extent,
    sh_colours,
    starting_points,
    strided_camera,
)

ADAM_EPS = 1e-15
"""Adam's epsilon for the Gaussians' parameters (3DGS's ``training_setup``)."""
ROWS: dict[str, str] = {
    "means": "means",
    "harmonics_dc": "harmonics",
    "harmonics_rest": "harmonics_rest",
    "opacity_logits": "opacities",
    "log_scales": "scales",
    "rotations": "rotations",
    "features": "features",
}
"""Per-Gaussian parameter -> its learning-rate group (``model.lr.<group>``)."""
INFO = "raster"
"""``ImageOutput.extras`` key of what the rasterizer reported of a training view (``ViewInfo``)."""


def rasterized(state: TrainingState) -> list[ViewInfo]:
    """What the rasterizer reported of each target view of the step (``ImageOutput.extras``)."""
    return [view.extras[INFO] for view in state.outputs.views if INFO in view.extras]


class Semantic3DGSHooks(FamilyHooks):
    """The start, the optimizer's options, the checkpoint's sizes and the step's schedule of ``Semantic3DGS``."""

    family: "Semantic3DGS"

    def initialise(self, scene: Scene) -> None:
        """The Gaussians from the scene's points (``gpnerf_core.starting_points``), unless weights were loaded
        already."""
        family = self.family
        gaussians = family.gaussians
        if gaussians.size:
            return
        points, _ = starting_points(scene, family.init_points, family.init_depth_stride)
        family.strategy_check_start(points.count)
        rows = rows_from_points(points.xyz, points.rgb, neighbour_scales(points.xyz), sh_degree=gaussians.sh_degree,
                                opacity=family.init_opacity)
        rows["features"] = colour_to_dc(torch.rand(points.count, gaussians.channels["features"]))  # Gaussian Grouping
        gaussians.set_rows({name: value.to(gaussians.means.device) for name, value in rows.items()})
        gaussians.extent.fill_(scene_extent(scene))

    def resize_to(self, weights: Mapping[str, Tensor], source: str) -> None:
        self.family.gaussians.take_sizes(weights, "gaussians.", source)

    def optimizer_options(self, total_steps: int) -> dict[str, GroupOptions]:
        """3DGS's epsilon for every Gaussian group; the centres' rate times the scene's extent, decayed log-linearly
        to ``means_final_ratio`` of it at ``total_steps`` (3DGS's ``get_expon_lr_func`` without delay)."""
        family = self.family
        ratio = family.means_final_ratio

        def means(step: int) -> float:
            t = min(1.0, (step + 1) / max(1, total_steps))
            return float(family.gaussians.extent) * math.exp(math.log(ratio) * t)

        options = {group: GroupOptions(eps=ADAM_EPS) for group in family.parameter_groups() if group != "head"}
        options["means"] = GroupOptions(lr_factor=means, eps=ADAM_EPS)
        return options

    def callbacks(self) -> Sequence[TrainingCallback]:
        return (TrainingCallback(TrainingPhase.BEFORE_STEP, self._colour_degree),
                TrainingCallback(TrainingPhase.BEFORE_BACKWARD, self._keep_gradients),
                TrainingCallback(TrainingPhase.AFTER_BACKWARD, self._density_control),
                TrainingCallback(TrainingPhase.AFTER_STEP, self._check_finite))

    def _colour_degree(self, state: TrainingState) -> None:
        """The colour's degree for this step (3DGS raises it at every ``sh_degree_every``-th iteration)."""
        gaussians = self.family.gaussians
        every = scaled_step(self.family.sh_degree_every, state.total_steps, self.family.strategy.schedule_steps)
        gaussians.active_degree.fill_(min(gaussians.sh_degree, (state.step + 1) // every))

    def _keep_gradients(self, state: TrainingState) -> None:
        """The strategy keeps the projected centres' gradients of the step's views."""
        gaussians = self.family.gaussians
        self.family.strategy.step_pre_backward(gaussians, state.optimizer, gaussians.row_state(), state.step,
                                               rasterized(state))

    def _density_control(self, state: TrainingState) -> None:
        """The strategy's statistics and density changes, told what the rasterizer reported of the step's views."""
        gaussians = self.family.gaussians
        self.family.strategy.scaled(state.total_steps).step_post_backward(
            gaussians, state.optimizer, gaussians.row_state(), state.step, rasterized(state))

    def _check_finite(self, state: TrainingState) -> None:
        """NaN or Inf in a Gaussian parameter stops training, naming it and the step."""
        gaussians = self.family.gaussians
        for name, tensor in gaussians.rows().items():
            finite = torch.isfinite(tensor.detach())
            if not bool(finite.all()):
                bad = int((~finite).reshape(finite.shape[0], -1).any(dim=1).sum()) if tensor.ndim else 1
                raise NonFiniteError(f"step {state.step}: model 'semantic_3dgs' Gaussian parameter {name!r} holds NaN "
                                     f"or Inf ({bad} of {gaussians.size} Gaussians); training stopped")


class Semantic3DGS(ModelFamily):
    """One scene's semantic 3D Gaussians (the module docstring).

    Args:
        head: the perception head decoding the rendered feature map, or None (a 1 x 1 convolution to the classes).
        num_classes: K (0 without a head: colour and depth only).
        strategy: the density control (``DefaultStrategy`` or ``BudgetedStrategy``) at its official step numbers.
        sh_degree_every: the colour's degree rises every this many official steps (scaled as the strategy's).
        the rest: ``Semantic3DGSConfig``'s fields.
    """

    capabilities = Capabilities(generalizable=False, trains_on=TrainingBatch.IMAGES, source_encoding=None,
                                changes_size=True, gaussians=True, hooks=Semantic3DGSHooks)

    def __init__(self, *, head: PerceptionHead | None, num_classes: int, sh_degree: int, feature_dim: int,
                 init_points: int, init_depth_stride: int, init_opacity: float, strategy: DefaultStrategy,
                 sh_degree_every: int, means_final_ratio: float, background: float, rasterizer: str) -> None:
        super().__init__()
        self.head = head
        self.num_classes = 0 if head is not None else int(num_classes)
        decoded = head is not None or self.num_classes > 0
        self.gaussians = GaussianParameters(sh_degree, {"features": feature_dim if decoded else 0})
        self.strategy = strategy
        strategy.initialize_state(self.gaussians)
        self.classifier = nn.Conv2d(feature_dim, self.num_classes, 1) if head is None and self.num_classes else None
        self.init_points, self.init_depth_stride = int(init_points), int(init_depth_stride)
        self.init_opacity = float(init_opacity)
        self.sh_degree_every = int(sh_degree_every)
        self.means_final_ratio = float(means_final_ratio)
        self.background, self.rasterizer = float(background), str(rasterizer)

    def strategy_check_start(self, count: int) -> None:
        """A strategy with a budget refuses a start above it."""
        check = getattr(self.strategy, "check_start", None)
        if check is not None:
            check(count)

    # ---- what the model is ------------------------------------------------------------------------------------------

    @property
    def semantic_output(self) -> SemanticOutput | None:
        return labels_or_head_output(self.head, self.num_classes)

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Each Gaussian parameter in its own group (``model.lr.<group>``: ``means``, ``harmonics``, ...); the
        classifier or the head under ``head`` (``model.lr.head``)."""
        rows = self.gaussians.rows()
        groups = {group: [rows[name]] for name, group in ROWS.items()}
        decoder = self.head if self.head is not None else self.classifier
        if decoder is not None:
            groups["head"] = list(decoder.parameters())
        return groups

    # ---- rendering --------------------------------------------------------------------------------------------------

    def render(self, camera: TargetCamera, stride: int, *, semantic: bool
               ) -> tuple[Tensor, Tensor, Tensor, Tensor | None, ViewInfo]:
        """``(rgb [h, w, 3], depth [h, w], alpha [h, w], features [h, w, F] or None, info)`` of ``camera`` on a
        ``stride`` grid, in one rasterization; ``info``: what the rasterizer reported (density control's input)."""
        if not self.gaussians.size:
            raise ConfigError("model=semantic_3dgs has no Gaussians: it is fitted on its scene first (run), or built "
                              "from a checkpoint")
        field = self.gaussians
        colours = sh_colours(field.harmonics(), field.means - camera.c2w[:3, 3].to(field.means.dtype))
        features = torch.cat([colours, field.features], dim=-1) if semantic and field.channels["features"] else colours
        background = torch.zeros(features.shape[1], dtype=features.dtype, device=features.device)
        background[:3] = self.background
        intrinsics, height, width = strided_camera(camera, stride)
        out = rasterize_gaussians(field.activated(features), intrinsics=intrinsics, c2w=camera.c2w, height=height,
                                  width=width, background=background, backend=self.rasterizer)
        depth = torch.where(out.alpha > 1e-6, out.depth / out.alpha.clamp_min(1e-6), torch.zeros_like(out.depth))
        semantic_map = out.features[..., 3:] if features.shape[1] > 3 else None
        info = ViewInfo(means2d=out.means2d, radii=out.radii, height=height, width=width)
        return out.features[..., :3], depth, out.alpha, semantic_map, info

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
        rgb, depth, alpha, semantic_map, info = self.render(target.camera, 1, semantic=decodes)
        extras = {INFO: info} if self.training else {}
        if not decodes:
            return ImageOutput(rgb=rgb, depth=depth, alpha=alpha, extras=extras)
        logits = self._decode(semantic_map, target.camera.image_size)
        if self.head is None:  # label rendering: the per-pixel scores
            return ImageOutput(rgb=rgb, depth=depth, alpha=alpha, scores=logits, extras=extras)
        return ImageOutput(rgb=rgb, depth=depth, alpha=alpha, semantic=semantic_map.permute(2, 0, 1)[None],
                           logits=logits, extras=extras)

    @torch.inference_mode()
    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: object = None) -> Prediction:
        """The view rasterized on a ``stride`` grid (0: every pixel); ``sources``, ``chunk_rays`` and ``features``
        are unused (a per-scene model renders from its own Gaussians in one call)."""
        stride = stride or 1
        decodes = self.head is not None or self.classifier is not None
        rgb, depth, _, semantic_map, _ = self.render(camera, stride, semantic=decodes)
        logits = self._decode(semantic_map, camera.image_size) if decodes else None
        semantic = semantic_map.permute(2, 0, 1) if semantic_map is not None else None
        return Prediction(rgb=rgb, depth=depth, semantic=semantic, logits=logits, stride=stride)

    @torch.inference_mode()
    def scene_gaussians(self, sources: SourceViews | None, *, near: float, far: float,
                        features: object = None) -> GaussianScene:
        """The scene's Gaussians, each labelled with the class its own feature is decoded to by the 1 x 1
        convolution (Gaussian Grouping's 3D classification); -1 with a head (it decodes maps, with context) or
        without semantics."""
        field = self.gaussians
        labels = None
        if self.classifier is not None:
            weight = self.classifier.weight[:, :, 0, 0]
            labels = (field.features @ weight.T + self.classifier.bias).argmax(dim=-1)
        return field.as_scene(labels)
