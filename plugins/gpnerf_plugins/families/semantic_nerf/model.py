"""Semantic-NeRF (Zhi et al., ICCV 2021; official code ``Harry-Zhi/semantic_nerf``) as a per-scene family.

One scene's field, fitted on that scene's training frames and rendered from its own parameters (no source views):

- **Encoding**: positions multiplied by ``position_scale`` (the official code divides by 10), then NeRF's positional
  encoding ``[x, sin(2^k x), cos(2^k x)]``, k < 10 (63 channels); unit view directions with 4 octaves (27 channels).
- **Trunk**: ``depth`` ReLU layers of ``width``, the encoded position concatenated after layer ``skip``.
- **Heads**: density ``Linear(width, 1)``, raw (ReLU at render time, after noise of std ``density_noise`` in training);
  semantics ``Linear(width, width/2)``, ReLU, ``Linear(width/2, K)``, view-independent; colour ``Linear(width, width)``
  concatenated with the encoded direction, ``Linear(. , width/2)``, ReLU, ``Linear(width/2, 3)``, sigmoid.
- **Rendering**: ``alpha = 1 - exp(-ReLU(sigma) * delta * |d|)`` with the last interval 1e10; colour, depth and the
  class **logits** composited with the weights (label rendering); the prediction is their argmax.
- **Coarse and fine**: separate networks; ``coarse_samples`` stratified samples uniform in depth between near and far
  (jittered in training), the fine network on those plus ``fine_samples`` importance samples of the coarse weights.
- **Loss** (the experiment ``baselines/semantic_nerf``): colour MSE of both passes + 0.04 x cross-entropy of both.

What changed for two CPU cores (each also in ``SemanticNeRFConfig``): width 256 -> 128, trunk 8 -> 6 layers (the skip
kept), samples 64 + 128 -> 32 + 32, 1024 -> 256 rays a step, and the step budget (the official 200k steps take hours on
a GPU). The classes are the dataset's, not remapped per scene as the official loaders do (a scene's absent classes are
simply never predicted there; the metrics score present classes, as for every family here).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from gpnerf_core import (
    ConfigError,
    FeatureMaps,
    ModelFamily,
    Prediction,
    Predicts,
    RayBatch,
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
    composite,
    importance_depths,
    points_along_rays,
    rays_through_pixels,
    render_whole_view,
    stratified_depths,
)
from gpnerf_plugins.families.nerf_field import NeRFField, check_field_options, density_weights, encoded_inputs


class SemanticNeRF(ModelFamily):
    """Semantic-NeRF: coarse and fine fields of one scene, label rendering (module docstring).

    Args:
        num_classes: K (0: colour and depth only).
        coarse_samples, fine_samples: samples per ray of the coarse pass, importance samples added for the fine one
            (0: one pass).
        width, depth, skip, position_scale, position_frequencies, direction_frequencies, density_noise, inverse_depth:
            ``SemanticNeRFConfig``'s.
    """

    generalizable = False
    accepts_head = False

    def __init__(self, *, num_classes: int, coarse_samples: int, fine_samples: int, width: int, depth: int, skip: int,
                 position_scale: float, position_frequencies: int, direction_frequencies: int, density_noise: float,
                 inverse_depth: bool) -> None:
        super().__init__()
        check_field_options(coarse_samples=coarse_samples, fine_samples=fine_samples, width=width, depth=depth,
                            skip=skip, position_scale=position_scale, position_frequencies=position_frequencies,
                            direction_frequencies=direction_frequencies, density_noise=density_noise)
        self.num_classes = int(num_classes)
        self.coarse_samples, self.fine_samples = int(coarse_samples), int(fine_samples)
        self.position_scale, self.density_noise = float(position_scale), float(density_noise)
        self.position_frequencies, self.direction_frequencies = int(position_frequencies), int(direction_frequencies)
        self.inverse_depth = bool(inverse_depth)
        def field() -> NeRFField:
            semantic = nn.Sequential(nn.Linear(width, width // 2), nn.ReLU(), nn.Linear(width // 2, self.num_classes))
            return NeRFField(width=width, depth=depth, skip=skip, position_dim=3 * (1 + 2 * position_frequencies),
                             direction_dim=3 * (1 + 2 * direction_frequencies),
                             branch=semantic if self.num_classes else None)

        self.coarse = field()
        self.fine = field() if fine_samples else None

    # ---- what the model is ------------------------------------------------------------------------------------------

    @property
    def semantic_output(self) -> SemanticOutput | None:
        if not self.num_classes:
            return None
        return SemanticOutput(Predicts.CLASSES, SemanticMode.LABEL_RENDERING, self.num_classes)

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Everything is the scene's own field (``train.lr.field``; Semantic-NeRF: 5e-4)."""
        return {"field": list(self.parameters())}

    def output_owners(self, names: dict[str, str]) -> dict[str, str]:
        field = f"model {names.get('model', 'semantic_nerf')!r} (its coarse and fine fields)"
        return {"colour": field, "depth": field, "logits": field}

    def encode(self, images: Tensor) -> FeatureMaps:
        raise ConfigError("semantic_nerf is a per-scene model: it encodes no source views")

    # ---- rendering ---------------------------------------------------------------------------------------------------

    def _pass(self, field: NeRFField, rays: RayBatch, samples: RaySamples, semantics: bool,
              generator: torch.Generator | None) -> RenderedRays:
        count = samples.depths.shape[1]
        position, direction, norms = encoded_inputs(samples.points, rays.directions, count, self.position_scale,
                                                    self.position_frequencies, self.direction_frequencies)
        raw, colour, scores = field(position, direction, semantics)
        weights = density_weights(raw.view(-1, count), samples.depths, norms, self.density_noise, generator)
        logits = composite(weights, scores.view(-1, count, self.num_classes)) if scores is not None else None
        return RenderedRays(rgb=composite(weights, colour.view(-1, count, 3)), weights=weights,
                            depth=(weights * samples.depths).sum(-1), samples=samples, logits=logits)

    def render_rays(self, rays: RayBatch, semantics: bool,
                    generator: torch.Generator | None) -> tuple[RenderedRays, RenderedRays | None]:
        """The coarse pass and (with fine samples) the fine pass on coarse + importance samples; ``generator`` None
        renders deterministically (no jitter, no density noise)."""
        depths = stratified_depths(rays, self.coarse_samples, inverse=self.inverse_depth, generator=generator)
        coarse = self._pass(self.coarse, rays, points_along_rays(rays, depths), semantics, generator)
        if self.fine is None:
            return coarse, None
        extra = importance_depths(depths, coarse.weights, self.fine_samples, deterministic=generator is None,
                                  generator=generator)
        samples = points_along_rays(rays, torch.cat([depths, extra], -1))
        return coarse, self._pass(self.fine, rays, samples, semantics, generator)

    # ---- the contract ------------------------------------------------------------------------------------------------

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        return StepOutput(tuple(self._forward_view(view, semantics) for view in batch.views))

    def _forward_view(self, view: TargetView, semantics: bool) -> ViewOutput:
        camera = view.camera
        rays = rays_through_pixels(view.pixels, camera.intrinsics, camera.c2w, camera.near, camera.far)
        generator = torch.Generator(device=view.pixels.device).manual_seed(view.render_seed) if self.training else None
        coarse, fine = self.render_rays(rays, semantics and self.num_classes > 0, generator)
        return ViewOutput(coarse=coarse, fine=fine)

    @torch.inference_mode()
    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: FeatureMaps | None = None) -> Prediction:
        def render(rays: RayBatch) -> RenderedRays:
            coarse, fine = self.render_rays(rays, self.num_classes > 0, None)
            return fine if fine is not None else coarse

        return render_whole_view(camera, render, stride=stride, chunk_rays=chunk_rays)
