"""NeRF's per-scene field, shared by the per-scene families (Semantic-NeRF, DM-NeRF): the positional encoding, the
MLP (trunk with a skip, raw density, view-dependent colour, a family's own branch on the trunk features), the weights
of its densities along a ray, and ``PerSceneNeRF``, the family body both subclass."""

from __future__ import annotations

from typing import Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import (
    ConfigError,
    FeatureMaps,
    ModelFamily,
    Prediction,
    RayBatch,
    RaySamples,
    RenderedRays,
    SourceViews,
    StepBatch,
    StepOutput,
    TargetCamera,
    TargetView,
    ViewOutput,
    composite,
    compositing_weights,
    density_opacity,
    importance_depths,
    points_along_rays,
    rays_through_pixels,
    render_whole_view,
    stratified_depths,
)


def positional_encoding(x: Tensor, octaves: int) -> Tensor:
    """NeRF's encoding ``[x, sin(2^0 x), cos(2^0 x), ..., sin(2^(L-1) x), cos(2^(L-1) x)]``: ``[..., 3]`` ->
    ``[..., 3 (1 + 2L)]``."""
    parts = [x]
    for octave in range(octaves):
        parts += [torch.sin(x * 2.0**octave), torch.cos(x * 2.0**octave)]
    return torch.cat(parts, -1)


class NeRFField(nn.Module):
    """The MLP of one pass: encoded position -> raw density, a branch's outputs (on the trunk features, detached with
    ``detach_branch`` so the branch's loss never shapes the geometry: DM-NeRF's object field) and, with the encoded
    view direction, colour.

    Args:
        width, depth, skip: the trunk: ``depth`` ReLU layers of ``width``, the encoded position concatenated after
            layer ``skip`` (0-based; NeRF's 4).
        position_dim, direction_dim: the encodings' channels.
        branch: a module from ``[N, width]`` trunk features, or None.
        detach_branch: the branch reads the trunk features detached.
    """

    def __init__(self, *, width: int, depth: int, skip: int, position_dim: int, direction_dim: int,
                 branch: nn.Module | None = None, detach_branch: bool = False) -> None:
        super().__init__()
        self.skip, self.detach_branch = skip, detach_branch
        self.trunk = nn.ModuleList(
            [nn.Linear(position_dim, width)]
            + [nn.Linear(width + (position_dim if i == skip + 1 else 0), width) for i in range(1, depth)])
        self.density = nn.Linear(width, 1)
        self.branch = branch
        self.feature = nn.Linear(width, width)
        self.colour = nn.Sequential(nn.Linear(width + direction_dim, width // 2), nn.ReLU(), nn.Linear(width // 2, 3))

    def forward(self, position: Tensor, direction: Tensor, with_branch: bool) -> tuple[Tensor, Tensor, Tensor | None]:
        """``[N, P]`` encoded positions and ``[N, D]`` encoded directions -> raw density ``[N]``, colour ``[N, 3]`` in
        [0, 1] and the branch's output (None unless ``with_branch``)."""
        h = position
        for index, layer in enumerate(self.trunk):
            h = F.relu(layer(h))
            if index == self.skip:
                h = torch.cat([position, h], -1)
        colour = torch.sigmoid(self.colour(torch.cat([self.feature(h), direction], -1)))
        out = None
        if with_branch and self.branch is not None:
            out = self.branch(h.detach() if self.detach_branch else h)
        return self.density(h)[..., 0], colour, out


def check_field_options(**options: float) -> None:
    """One ConfigError naming every out-of-range option of a per-scene field (``model.<key>=<value>: expected ...``)."""
    depth = options["depth"]
    rules = {
        "coarse_samples": (lambda v: v >= 2, ">= 2"),
        "fine_samples": (lambda v: v >= 0, ">= 0"),
        "width": (lambda v: v >= 2 and v % 2 == 0, "an even number >= 2"),
        "depth": (lambda v: v >= 2, ">= 2"),
        "skip": (lambda v: 0 <= v < depth - 1, f"in [0, model.depth - 1) = [0, {depth - 1})"),
        "position_scale": (lambda v: v > 0, "> 0"),
        "position_frequencies": (lambda v: v >= 0, ">= 0"),
        "direction_frequencies": (lambda v: v >= 0, ">= 0"),
        "density_noise": (lambda v: v >= 0, ">= 0"),
    }
    problems = [f"model.{key}={value}: expected {rules[key][1]}" for key, value in options.items()
                if key in rules and not rules[key][0](value)]
    if problems:
        raise ConfigError("; ".join(problems))


def encoded_inputs(samples_points: Tensor, directions: Tensor, count: int, position_scale: float,
                   position_frequencies: int, direction_frequencies: int) -> tuple[Tensor, Tensor, Tensor]:
    """The encoded positions ``[R * S, P]`` (scaled by ``position_scale``), each sample's encoded unit direction
    ``[R * S, D]`` and the rays' lengths per unit of depth ``[R]`` (``|d|``: depth here is camera z)."""
    norms = directions.norm(dim=-1)
    position = positional_encoding(samples_points.reshape(-1, 3) * position_scale, position_frequencies)
    direction = positional_encoding(directions / norms[:, None], direction_frequencies)
    direction = direction[:, None].expand(-1, count, -1).reshape(-1, direction.shape[-1])
    return position, direction, norms


def density_weights(raw: Tensor, depths: Tensor, norms: Tensor, noise: float,
                    generator: torch.Generator | None) -> Tensor:
    """NeRF's ``raw2outputs`` weights ``[R, S]``: ``alpha = 1 - exp(-ReLU(raw + noise) * delta * |d|)``, the last
    interval 1e10; Gaussian noise of std ``noise`` on the raw density only with a ``generator`` (training)."""
    if generator is not None and noise > 0:
        raw = raw + noise * torch.randn(raw.shape, generator=generator, device=raw.device, dtype=raw.dtype)
    return compositing_weights(density_opacity(F.relu(raw) * norms[:, None], depths))


class PerSceneNeRF(ModelFamily):
    """A per-scene NeRF family's shared body: coarse and fine ``NeRFField`` s of one scene, a branch per field (a
    family's scores), samples uniform in depth (or 1/depth) plus importance samples, and the unchanged training and
    whole-view contract. A subclass gives the branch (``make_branch``), how its per-sample outputs are composited
    (``composite_branch``) and its ``semantic_output``.

    Args:
        coarse_samples, fine_samples: samples of the coarse pass and importance samples added for the fine one (0: one
            pass).
        width, depth, skip, position_scale, position_frequencies, direction_frequencies, density_noise, inverse_depth:
            the field and its sampling (``check_field_options``).
        detach_branch: the branch reads the trunk features detached (its loss never shapes the geometry).
    """

    generalizable = False
    accepts_head = False

    def __init__(self, *, coarse_samples: int, fine_samples: int, width: int, depth: int, skip: int,
                 position_scale: float, position_frequencies: int, direction_frequencies: int, density_noise: float,
                 inverse_depth: bool, detach_branch: bool = False) -> None:
        super().__init__()
        check_field_options(coarse_samples=coarse_samples, fine_samples=fine_samples, width=width, depth=depth,
                            skip=skip, position_scale=position_scale, position_frequencies=position_frequencies,
                            direction_frequencies=direction_frequencies, density_noise=density_noise)
        self.coarse_samples, self.fine_samples = int(coarse_samples), int(fine_samples)
        self.position_scale, self.density_noise = float(position_scale), float(density_noise)
        self.position_frequencies, self.direction_frequencies = int(position_frequencies), int(direction_frequencies)
        self.inverse_depth = bool(inverse_depth)

        def field() -> NeRFField:
            return NeRFField(width=width, depth=depth, skip=skip, position_dim=3 * (1 + 2 * position_frequencies),
                             direction_dim=3 * (1 + 2 * direction_frequencies), branch=self.make_branch(width),
                             detach_branch=detach_branch)

        self.coarse = field()
        self.fine = field() if fine_samples else None

    # ---- what a subclass says ---------------------------------------------------------------------------------------

    def make_branch(self, width: int) -> nn.Module | None:
        """The branch of one field on its ``[N, width]`` trunk features (None: colour and depth only)."""
        return None

    def composite_branch(self, weights: Tensor, outputs: Tensor) -> Tensor:
        """The per-ray scores ``[R, X]`` of per-sample branch outputs ``[R, S, X]`` (label rendering)."""
        return composite(weights, outputs)

    # ---- what the model is ------------------------------------------------------------------------------------------

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Everything is the scene's own field (``train.lr.field``)."""
        return {"field": list(self.parameters())}

    def output_owners(self, names: Mapping[str, str]) -> dict[str, str]:
        field = f"model {names.get('model', type(self).__name__)!r} (its coarse and fine fields)"
        return {"colour": field, "depth": field, "logits": field}

    def encode(self, images: Tensor) -> FeatureMaps:
        raise ConfigError(f"{type(self).__name__} is a per-scene model: it encodes no source views")

    # ---- rendering ---------------------------------------------------------------------------------------------------

    def _pass(self, field: NeRFField, rays: RayBatch, samples: RaySamples, branch: bool, per_sample: bool,
              generator: torch.Generator | None) -> RenderedRays:
        count = samples.depths.shape[1]
        position, direction, norms = encoded_inputs(samples.points, rays.directions, count, self.position_scale,
                                                    self.position_frequencies, self.direction_frequencies)
        raw, colour, outputs = field(position, direction, branch)
        weights = density_weights(raw.view(-1, count), samples.depths, norms, self.density_noise, generator)
        logits = per_sample_outputs = None
        if outputs is not None:
            per_sample_outputs = outputs.view(-1, count, outputs.shape[-1])
            logits = self.composite_branch(weights, per_sample_outputs)
        return RenderedRays(rgb=composite(weights, colour.view(-1, count, 3)), weights=weights,
                            depth=(weights * samples.depths).sum(-1), samples=samples, logits=logits,
                            sample_semantic=per_sample_outputs if per_sample else None)

    def render_rays(self, rays: RayBatch, branch: bool, generator: torch.Generator | None,
                    per_sample: bool = False) -> tuple[RenderedRays, RenderedRays | None]:
        """The coarse pass and (with fine samples) the fine pass on coarse + importance samples; ``generator`` None
        renders deterministically (no jitter, no density noise). ``branch``: composite the branch's scores;
        ``per_sample``: also return them per sample (``RenderedRays.sample_semantic``)."""
        depths = stratified_depths(rays, self.coarse_samples, inverse=self.inverse_depth, generator=generator)
        coarse = self._pass(self.coarse, rays, points_along_rays(rays, depths), branch, per_sample, generator)
        if self.fine is None:
            return coarse, None
        extra = importance_depths(depths, coarse.weights, self.fine_samples, deterministic=generator is None,
                                  generator=generator)
        samples = points_along_rays(rays, torch.cat([depths, extra], -1))
        return coarse, self._pass(self.fine, rays, samples, branch, per_sample, generator)

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
