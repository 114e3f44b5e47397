"""DM-NeRF (Wang et al., ICLR 2023; official code ``vLAR-group/DM-NeRF``) as a per-scene instance family.

NeRF's field of one scene (``families/nerf_field.py``: the positional encoding without scaling, trunk with a skip,
density, view-dependent colour; coarse and fine networks) plus DM-NeRF's **object field**: on the trunk features,
**detached** (instance gradients never shape the geometry), ``Linear(width, width)``, ``Linear(width, width / 2)``,
ReLU, ``Linear(width / 2, K + 1)``: K object slots and an "empty" one. The object logits are composited along the ray
with the **detached** weights; the slot probabilities are each slot's own **sigmoid after** compositing (no softmax
across slots), the empty slot dropped: ``SemanticOutput.slot_activation = "sigmoid"``. The per-sample logits go to the
loss set (``RenderedRays.sample_semantic``) for DM-NeRF's 3D emptiness penalty (``losses/dm_nerf.py``).

What changed for two CPU cores, as for Semantic-NeRF (``families/semantic_nerf``): width 256 -> 128, trunk 8 -> 6
(the skip kept), samples 64 + 128 -> 32 + 32, 3072 -> 512 rays a step, and the step budget (500k official).
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


def object_branch(width: int, slots: int) -> nn.Module:
    """DM-NeRF's object head: ``Linear(width, width)``, ``Linear(width, width / 2)``, ReLU, ``Linear(width / 2,
    slots + 1)``."""
    return nn.Sequential(nn.Linear(width, width), nn.Linear(width, width // 2), nn.ReLU(),
                         nn.Linear(width // 2, slots + 1))


class DMNeRF(ModelFamily):
    """DM-NeRF: coarse and fine fields of one scene with an object field (module docstring).

    Args:
        slots: K object slots (K + 1 outputs, the last "empty").
        the rest: ``DMNeRFConfig``'s.
    """

    generalizable = False
    accepts_head = False

    def __init__(self, *, slots: int, coarse_samples: int, fine_samples: int, width: int, depth: int, skip: int,
                 position_scale: float, position_frequencies: int, direction_frequencies: int, density_noise: float,
                 inverse_depth: bool) -> None:
        super().__init__()
        if isinstance(slots, bool) or not isinstance(slots, int) or slots < 1:
            raise ConfigError(f"model.slots={slots!r}: expected an integer >= 1 (object slots)")
        check_field_options(coarse_samples=coarse_samples, fine_samples=fine_samples, width=width, depth=depth,
                            skip=skip, position_scale=position_scale, position_frequencies=position_frequencies,
                            direction_frequencies=direction_frequencies, density_noise=density_noise)
        self.slots = slots
        self.coarse_samples, self.fine_samples = int(coarse_samples), int(fine_samples)
        self.position_scale, self.density_noise = float(position_scale), float(density_noise)
        self.position_frequencies, self.direction_frequencies = int(position_frequencies), int(direction_frequencies)
        self.inverse_depth = bool(inverse_depth)

        def field() -> NeRFField:
            return NeRFField(width=width, depth=depth, skip=skip, position_dim=3 * (1 + 2 * position_frequencies),
                             direction_dim=3 * (1 + 2 * direction_frequencies), branch=object_branch(width, slots),
                             detach_branch=True)

        self.coarse = field()
        self.fine = field() if fine_samples else None

    # ---- what the model is ------------------------------------------------------------------------------------------

    @property
    def semantic_output(self) -> SemanticOutput:
        return SemanticOutput(Predicts.INSTANCES, SemanticMode.LABEL_RENDERING, self.slots + 1, self.slots,
                              slot_activation="sigmoid")

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Everything is the scene's own field (``train.lr.field``; DM-NeRF: 5e-4)."""
        return {"field": list(self.parameters())}

    def output_owners(self, names: dict[str, str]) -> dict[str, str]:
        field = f"model {names.get('model', 'dm_nerf')!r} (its coarse and fine fields)"
        return {"colour": field, "depth": field, "logits": f"{field}' object field"}

    def encode(self, images: Tensor) -> FeatureMaps:
        raise ConfigError("dm_nerf is a per-scene model: it encodes no source views")

    # ---- rendering ---------------------------------------------------------------------------------------------------

    def _pass(self, field: NeRFField, rays: RayBatch, samples: RaySamples, objects: bool, per_sample: bool,
              generator: torch.Generator | None) -> RenderedRays:
        count = samples.depths.shape[1]
        position, direction, norms = encoded_inputs(samples.points, rays.directions, count, self.position_scale,
                                                    self.position_frequencies, self.direction_frequencies)
        raw, colour, logits = field(position, direction, objects)
        weights = density_weights(raw.view(-1, count), samples.depths, norms, self.density_noise, generator)
        rendered = sample_logits = None
        if logits is not None:
            sample_logits = logits.view(-1, count, self.slots + 1)
            rendered = composite(weights.detach(), sample_logits)  # DM-NeRF renders the objects with fixed weights
        return RenderedRays(rgb=composite(weights, colour.view(-1, count, 3)), weights=weights,
                            depth=(weights * samples.depths).sum(-1), samples=samples, logits=rendered,
                            sample_semantic=sample_logits if per_sample else None)

    def render_rays(self, rays: RayBatch, objects: bool, generator: torch.Generator | None,
                    per_sample: bool = False) -> tuple[RenderedRays, RenderedRays | None]:
        """The coarse pass and (with fine samples) the fine pass on coarse + importance samples; ``generator`` None
        renders deterministically. ``per_sample``: also return each sample's object logits (the emptiness penalty)."""
        depths = stratified_depths(rays, self.coarse_samples, inverse=self.inverse_depth, generator=generator)
        coarse = self._pass(self.coarse, rays, points_along_rays(rays, depths), objects, per_sample, generator)
        if self.fine is None:
            return coarse, None
        extra = importance_depths(depths, coarse.weights, self.fine_samples, deterministic=generator is None,
                                  generator=generator)
        samples = points_along_rays(rays, torch.cat([depths, extra], -1))
        return coarse, self._pass(self.fine, rays, samples, objects, per_sample, generator)

    # ---- the contract ------------------------------------------------------------------------------------------------

    def forward(self, batch: StepBatch, *, semantics: bool, sample_semantics: bool = False) -> StepOutput:
        return StepOutput(tuple(self._forward_view(view, semantics, sample_semantics) for view in batch.views))

    def _forward_view(self, view: TargetView, semantics: bool, sample_semantics: bool) -> ViewOutput:
        camera = view.camera
        rays = rays_through_pixels(view.pixels, camera.intrinsics, camera.c2w, camera.near, camera.far)
        generator = torch.Generator(device=view.pixels.device).manual_seed(view.render_seed) if self.training else None
        coarse, fine = self.render_rays(rays, semantics, generator, per_sample=sample_semantics)
        return ViewOutput(coarse=coarse, fine=fine)

    @torch.inference_mode()
    def predict(self, camera: TargetCamera, sources: SourceViews | None, *, stride: int, chunk_rays: int,
                features: FeatureMaps | None = None) -> Prediction:
        def render(rays: RayBatch) -> RenderedRays:
            coarse, fine = self.render_rays(rays, True, None)
            return fine if fine is not None else coarse

        return render_whole_view(camera, render, stride=stride, chunk_rays=chunk_rays)
