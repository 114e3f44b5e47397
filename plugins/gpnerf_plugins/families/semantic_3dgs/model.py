"""Per-scene semantic 3D Gaussian splatting: ``model=semantic_3dgs`` (docs/families/semantic_3dgs.md).

3D Gaussian splatting (Kerbl, Kopanas, Leimkuehler, Drettakis, SIGGRAPH 2023; official code
``graphdeco-inria/gaussian-splatting``) fitted on one scene's training frames, with a semantic feature per Gaussian as
Feature 3DGS (Zhou et al., CVPR 2024) and Gaussian Grouping (Ye et al., ECCV 2024) carry one:

- **Start** (``initialise``, ``initial.py``): the scene's sparse points (a capture's structure from motion) or its
  training frames' depth back-projected, at most ``init_points``; colour as the degree-0 harmonic, isotropic scales
  from the three nearest neighbours, opacity 0.1; semantic features uniform as Gaussian Grouping's.
- **Render**: every Gaussian rasterized (``gpnerf_core.rasterize_gaussians``) with its colour from spherical harmonics
  up to the active degree (raised by one every ``sh_degree_every`` steps) seen from the camera, its semantic feature
  composited in the same pass; depth is the composited depth over the accumulated opacity.
- **Semantics**: without a ``+head`` the rendered feature map goes through a 1 x 1 convolution to class scores per
  pixel (Feature 3DGS's decoder, Gaussian Grouping's classifier: label rendering); with a head (``+head=unet``, or
  ``+head=instance`` for Gaussian Grouping's identities) the head decodes it.
- **Train** on whole images (the ``image`` loss set with ``rgb_error=l1``: 0.8 L1 + 0.2 D-SSIM, 3DGS's loss, plus the
  cross-entropy): Adam per parameter with 3DGS's rates and epsilon 1e-15, the centres' rate decayed log-linearly;
  between backward and the optimizer step, the densification statistics, densification and pruning on 3DGS's
  schedule, and opacity resets (``densify.py``), the schedule's steps scaled to ``train.steps``.

Its parameters change size while it trains (``changes_size``): checkpoints hold the Gaussians they have, and ``eval``,
``render``, ``view`` and ``export`` build it at a checkpoint's size (``resize_to``).
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import (
    ConfigError,
    GaussianScene,
    GroupOptions,
    ModelFamily,
    NonFiniteError,
    PerceptionHead,
    Prediction,
    RenderedRays,
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
    ViewOutput,
    colour_to_dc,
    decode_checked,
    labels_or_head_output,
    rasterize_gaussians,
    sh_colours,
    strided_camera,
)
from gpnerf_plugins.families.semantic_3dgs.densify import DensityControl, add_statistics, densify_and_prune, reset_opacity
from gpnerf_plugins.families.semantic_3dgs.field import ROWS, GaussianField
from gpnerf_plugins.families.semantic_3dgs.initial import neighbour_scales, scene_extent, starting_points

ADAM_EPS = 1e-15
"""Adam's epsilon for the Gaussians' parameters (3DGS's ``training_setup``)."""


def scaled_step(official: int, total_steps: int, schedule_steps: int) -> int:
    """An official schedule's step number for a run of ``total_steps`` (at least 1)."""
    return max(1, round(official * total_steps / schedule_steps))


class Semantic3DGS(ModelFamily):
    """One scene's semantic 3D Gaussians (the module docstring).

    Args:
        head: the perception head decoding the rendered feature map, or None (a 1 x 1 convolution to the classes).
        num_classes: K (0 without a head: colour and depth only).
        schedule: the official step numbers and their length (``Semantic3DGSConfig``'s ``schedule_steps``,
            ``densify_from``, ``densify_until``, ``densify_every``, ``opacity_reset_every``, ``sh_degree_every``).
        control: the densification thresholds.
        the rest: ``Semantic3DGSConfig``'s fields.
    """

    generalizable = False
    trains_on = TrainingBatch.IMAGES
    changes_size = True

    def __init__(self, *, head: PerceptionHead | None, num_classes: int, sh_degree: int, feature_dim: int,
                 init_points: int, init_depth_stride: int, init_opacity: float, schedule: Mapping[str, int],
                 control: DensityControl, means_final_ratio: float, background: float, rasterizer: str) -> None:
        super().__init__()
        self.head = head
        self.num_classes = 0 if head is not None else int(num_classes)
        decoded = head is not None or self.num_classes > 0
        self.gaussians = GaussianField(sh_degree, feature_dim if decoded else 0)
        self.classifier = nn.Conv2d(feature_dim, self.num_classes, 1) if head is None and self.num_classes else None
        self.init_points, self.init_depth_stride = int(init_points), int(init_depth_stride)
        self.init_opacity = float(init_opacity)
        self.schedule, self.control = dict(schedule), control
        self.means_final_ratio = float(means_final_ratio)
        self.background, self.rasterizer = float(background), str(rasterizer)
        self._views: list[tuple[Tensor, Tensor, int, int]] = []
        self._capped = [False]

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

    def output_owners(self, names: Mapping[str, str]) -> dict[str, str]:
        owners = super().output_owners(names)
        if self.head is not None:
            owners["logits"] = f"head {names.get('head')!r}"
        return owners

    def optimizer_options(self, total_steps: int) -> dict[str, GroupOptions]:
        """3DGS's epsilon for every Gaussian group; the centres' rate times the scene's extent, decayed log-linearly
        to ``means_final_ratio`` of it at ``total_steps`` (3DGS's ``get_expon_lr_func`` without delay)."""
        ratio = self.means_final_ratio

        def means(step: int) -> float:
            t = min(1.0, (step + 1) / max(1, total_steps))
            return float(self.gaussians.extent) * math.exp(math.log(ratio) * t)

        options = {group: GroupOptions(eps=ADAM_EPS) for group in self.parameter_groups() if group != "head"}
        options["means"] = GroupOptions(lr_factor=means, eps=ADAM_EPS)
        return options

    # ---- the scene's Gaussians --------------------------------------------------------------------------------------

    def initialise(self, scene: Scene) -> None:
        """The Gaussians from the scene's points (``initial.py``), unless weights were loaded already."""
        if self.gaussians.size:
            return
        points, _ = starting_points(scene, self.init_points, self.init_depth_stride)
        count = points.count
        device = self.gaussians.means.device
        rotations = torch.zeros(count, 4)
        rotations[:, 0] = 1.0
        feature_dim = self.gaussians.feature_dim
        rest = self.gaussians.harmonics_rest.shape[-1]
        values = {
            "means": points.xyz,
            "harmonics_dc": colour_to_dc(points.rgb),
            "harmonics_rest": torch.zeros(count, 3, rest),
            "opacity_logits": torch.full((count,), math.log(self.init_opacity / (1 - self.init_opacity))),
            "log_scales": neighbour_scales(points.xyz).log()[:, None].repeat(1, 3),
            "rotations": rotations,
            "features": colour_to_dc(torch.rand(count, feature_dim)),  # Gaussian Grouping's identity start
        }
        self.gaussians.set_rows({name: value.to(device) for name, value in values.items()})
        self.gaussians.extent.fill_(scene_extent(scene))

    def resize_to(self, weights: Mapping[str, Tensor], source: str) -> None:
        self.gaussians.take_sizes(weights, "gaussians.", source)

    # ---- the training loop's hooks ----------------------------------------------------------------------------------

    def training_callbacks(self) -> Sequence[TrainingCallback]:
        return (TrainingCallback(TrainingPhase.BEFORE_STEP, self._before_step),
                TrainingCallback(TrainingPhase.AFTER_BACKWARD, self._after_backward),
                TrainingCallback(TrainingPhase.AFTER_STEP, self._check_finite))

    def _step(self, name: str, state: TrainingState) -> int:
        return scaled_step(self.schedule[name], state.total_steps, self.schedule["schedule_steps"])

    def _before_step(self, state: TrainingState) -> None:
        """The colour's degree for this step (3DGS raises it at every ``sh_degree_every``-th iteration)."""
        self._views.clear()
        degree = min(self.gaussians.sh_degree, (state.step + 1) // self._step("sh_degree_every", state))
        self.gaussians.active_degree.fill_(degree)

    def _after_backward(self, state: TrainingState) -> None:
        """3DGS's density control, on its schedule (official iteration = step + 1)."""
        views, self._views = self._views, []
        iteration = state.step + 1
        if iteration >= self._step("densify_until", state):
            return
        for means2d, radii, height, width in views:
            add_statistics(self.gaussians, means2d, radii, height, width)
        reset_every = self._step("opacity_reset_every", state)
        if iteration > self._step("densify_from", state) and iteration % self._step("densify_every", state) == 0:
            densify_and_prune(self.gaussians, state.optimizer, self.control, iteration > reset_every, self._capped)
        if iteration % reset_every == 0:
            reset_opacity(self.gaussians, state.optimizer)

    def _check_finite(self, state: TrainingState) -> None:
        """NaN or Inf in a Gaussian parameter stops training, naming it and the step."""
        for name, tensor in self.gaussians.rows().items():
            finite = torch.isfinite(tensor.detach())
            if not bool(finite.all()):
                bad = int((~finite).reshape(finite.shape[0], -1).any(dim=1).sum()) if tensor.ndim else 1
                raise NonFiniteError(f"step {state.step}: model 'semantic_3dgs' Gaussian parameter {name!r} holds NaN "
                                     f"or Inf ({bad} of {self.gaussians.size} Gaussians); training stopped")

    # ---- rendering --------------------------------------------------------------------------------------------------

    def render(self, camera: TargetCamera, stride: int, *, semantic: bool, keep_statistics: bool = False
               ) -> tuple[Tensor, Tensor, Tensor | None]:
        """``(rgb [h, w, 3], depth [h, w], features [h, w, F] or None)`` of ``camera`` on a ``stride`` grid, in one
        rasterization; ``keep_statistics``: the projected centres are kept for the densification statistics."""
        if not self.gaussians.size:
            raise ConfigError("model=semantic_3dgs has no Gaussians: it is fitted on its scene first (run), or built "
                              "from a checkpoint")
        field = self.gaussians
        colours = sh_colours(field.harmonics(), field.means - camera.c2w[:3, 3].to(field.means.dtype))
        features = torch.cat([colours, field.features], dim=-1) if semantic and field.feature_dim else colours
        background = torch.zeros(features.shape[1], dtype=features.dtype, device=features.device)
        background[:3] = self.background
        intrinsics, height, width = strided_camera(camera, stride)
        out = rasterize_gaussians(field.activated(features), intrinsics=intrinsics, c2w=camera.c2w, height=height,
                                  width=width, background=background, backend=self.rasterizer)
        if keep_statistics and out.means2d.requires_grad:
            out.means2d.retain_grad()
            self._views.append((out.means2d, out.radii, height, width))
        depth = torch.where(out.alpha > 1e-6, out.depth / out.alpha.clamp_min(1e-6), torch.zeros_like(out.depth))
        semantic_map = out.features[..., 3:] if features.shape[1] > 3 else None
        return out.features[..., :3], depth, semantic_map

    def _decode(self, semantic_map: Tensor, size: tuple[int, int]) -> Tensor:
        """``[1, K, H, W]`` scores of ``[h, w, F]`` rendered features: the head's, or the 1 x 1 convolution's."""
        features = semantic_map.permute(2, 0, 1)[None]
        if self.head is not None:
            return decode_checked(self.head, features, size).logits
        logits = self.classifier(features)
        return logits if tuple(logits.shape[-2:]) == size else F.interpolate(logits, size=size, mode="nearest")

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        return StepOutput(tuple(self._forward_view(view, semantics) for view in batch.views))

    def _forward_view(self, target: TargetView, semantics: bool) -> ViewOutput:
        decodes = semantics and (self.head is not None or self.classifier is not None)
        rgb, depth, semantic_map = self.render(target.camera, 1, semantic=decodes, keep_statistics=self.training)
        rows, cols = target.pixels[:, 1].long(), target.pixels[:, 0].long()
        if not decodes:
            return ViewOutput(coarse=RenderedRays(rgb=rgb[rows, cols], depth=depth[rows, cols]), fine=None)
        logits = self._decode(semantic_map, target.camera.image_size)
        if self.head is None:  # label rendering: the per-pixel scores at the rays
            rendered = RenderedRays(rgb=rgb[rows, cols], depth=depth[rows, cols], logits=logits[0, :, rows, cols].T)
            return ViewOutput(coarse=rendered, fine=None)
        rendered = RenderedRays(rgb=rgb[rows, cols], depth=depth[rows, cols], semantic=semantic_map[rows, cols])
        return ViewOutput(coarse=rendered, fine=None, head_input=semantic_map.permute(2, 0, 1)[None], logits=logits)

    @torch.inference_mode()
    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: object = None) -> Prediction:
        """The view rasterized on a ``stride`` grid (0: every pixel); ``sources``, ``chunk_rays`` and ``features``
        are unused (a per-scene model renders from its own Gaussians in one call)."""
        stride = stride or 1
        decodes = self.head is not None or self.classifier is not None
        rgb, depth, semantic_map = self.render(camera, stride, semantic=decodes)
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
        labels = torch.full((field.size,), -1, dtype=torch.long, device=field.means.device)
        if self.classifier is not None:
            weight = self.classifier.weight[:, :, 0, 0]
            labels = (field.features @ weight.T + self.classifier.bias).argmax(dim=-1)
        harmonics = torch.cat([field.harmonics_dc[..., None], field.harmonics_rest], dim=-1)
        return GaussianScene(means=field.means, scales=field.log_scales.exp(),
                             rotations=field.rotations / field.rotations.norm(dim=-1, keepdim=True).clamp_min(1e-12),
                             opacities=torch.sigmoid(field.opacity_logits), harmonics=harmonics, labels=labels)
