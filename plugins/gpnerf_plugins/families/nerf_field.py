"""NeRF's per-scene field, shared by the per-scene families (Semantic-NeRF, DM-NeRF): the positional encoding, the
MLP (trunk with a skip, raw density, view-dependent colour, a family's own branch on the trunk features), the weights
of its densities along a ray, and ``PerSceneNeRF``, the family body both subclass, with its field either that MLP
(``field="mlp"``) or a hash grid (``field="grid"``: ``families/hash_grid.py``)."""

from __future__ import annotations

import math

from typing import Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import (
    Capabilities,
    ConfigError,
    FamilyHooks,
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
from gpnerf_plugins.families.hash_grid import HashGridField

FIELDS = ("mlp", "grid")
"""``model.field``: NeRF's positional-encoding MLP (the method's) or a multiresolution hash grid (``HashGridField``)."""


def positional_encoding(x: Tensor, octaves: int) -> Tensor:
    """NeRF's encoding ``[x, sin(2^0 x), cos(2^0 x), ..., sin(2^(L-1) x), cos(2^(L-1) x)]``: ``[..., 3]`` ->
    ``[..., 3 (1 + 2L)]``."""
    parts = [x]
    for octave in range(octaves):
        parts += [torch.sin(x * 2.0**octave), torch.cos(x * 2.0**octave)]
    return torch.cat(parts, -1)


class NeRFField(nn.Module):
    """The MLP of one pass: position -> positional encoding -> raw density, a branch's outputs (on the trunk features,
    detached with ``detach_branch`` so the branch's loss never shapes the geometry: DM-NeRF's object field) and, with
    the encoded view direction, colour.

    Args:
        width, depth, skip: the trunk: ``depth`` ReLU layers of ``width``, the encoded position concatenated after
            layer ``skip`` (0-based; NeRF's 4).
        position_frequencies: octaves of the position's encoding (``3 (1 + 2 L)`` channels).
        direction_dim: the encoded direction's channels.
        branch: a module from ``[N, width]`` trunk features, or None.
        detach_branch: the branch reads the trunk features detached.
    """

    def __init__(self, *, width: int, depth: int, skip: int, position_frequencies: int, direction_dim: int,
                 branch: nn.Module | None = None, detach_branch: bool = False) -> None:
        super().__init__()
        self.skip, self.detach_branch, self.position_frequencies = skip, detach_branch, position_frequencies
        position_dim = 3 * (1 + 2 * position_frequencies)
        self.trunk = nn.ModuleList(
            [nn.Linear(position_dim, width)]
            + [nn.Linear(width + (position_dim if i == skip + 1 else 0), width) for i in range(1, depth)])
        self.density = nn.Linear(width, 1)
        self.branch = branch
        self.feature = nn.Linear(width, width)
        self.colour = nn.Sequential(nn.Linear(width + direction_dim, width // 2), nn.ReLU(), nn.Linear(width // 2, 3))

    def forward(self, position: Tensor, direction: Tensor, with_branch: bool) -> tuple[Tensor, Tensor, Tensor | None]:
        """``[N, 3]`` positions (scaled) and ``[N, D]`` encoded directions -> raw density ``[N]``, colour ``[N, 3]`` in
        [0, 1] and the branch's output (None unless ``with_branch``)."""
        position = positional_encoding(position, self.position_frequencies)
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


MAX_FREQUENCIES = 30
"""Octaves of a positional encoding at most: 2^30 already exceeds float32's integer precision, and far more overflows."""


def check_field_options(**options: float) -> None:
    """One ConfigError naming every out-of-range option of a per-scene field (``model.<key>=<value>: expected ...``);
    every number must be finite (an infinite noise or scale trains NaN or overflows, never an error of its own)."""
    depth = options["depth"]
    finite = [key for key, value in options.items()
              if isinstance(value, float) and not math.isfinite(value)]
    if finite:
        raise ConfigError("; ".join(f"model.{key}={options[key]}: expected a finite number" for key in finite))
    rules = {
        "coarse_samples": (lambda v: v >= 2, ">= 2"),
        "fine_samples": (lambda v: v >= 0, ">= 0"),
        "width": (lambda v: v >= 2 and v % 2 == 0, "an even number >= 2"),
        "depth": (lambda v: v >= 2, ">= 2"),
        "skip": (lambda v: 0 <= v < depth - 1, f"in [0, model.depth - 1) = [0, {depth - 1})"),
        "position_scale": (lambda v: v > 0, "> 0"),
        "position_frequencies": (lambda v: 0 <= v <= MAX_FREQUENCIES, f"in [0, {MAX_FREQUENCIES}]"),
        "direction_frequencies": (lambda v: 0 <= v <= MAX_FREQUENCIES, f"in [0, {MAX_FREQUENCIES}]"),
        "density_noise": (lambda v: v >= 0, ">= 0"),
        "field": (lambda v: v in FIELDS, f"one of {', '.join(FIELDS)}"),
        "grid_levels": (lambda v: 1 <= v and v * 2 ** options.get("grid_table_log2", 0) <= 2**28,
                        ">= 1, with model.grid_levels x 2^model.grid_table_log2 <= 2^28 table entries"),
        "grid_features": (lambda v: v >= 1, ">= 1"),
        "grid_table_log2": (lambda v: 4 <= v <= 24, "in [4, 24] (2^table_log2 entries per level)"),
        "grid_base_resolution": (lambda v: v > 0, "> 0 cells per scaled unit"),
        "grid_finest_resolution": (lambda v: v >= options.get("grid_base_resolution", 0),
                                   ">= model.grid_base_resolution"),
        "grid_width": (lambda v: v >= 2 and v % 2 == 0, "an even number >= 2"),
    }
    problems = [f"model.{key}={value}: expected {rules[key][1]}" for key, value in options.items()
                if key in rules and not rules[key][0](value)]
    if problems:
        raise ConfigError("; ".join(problems))


def field_inputs(samples_points: Tensor, directions: Tensor, count: int, position_scale: float,
                 direction_frequencies: int) -> tuple[Tensor, Tensor, Tensor]:
    """The positions ``[R * S, 3]`` scaled by ``position_scale`` (each field encodes them its own way), each sample's
    encoded unit direction ``[R * S, D]`` and the rays' lengths per unit of depth ``[R]`` (``|d|``: depth here is
    camera z)."""
    norms = directions.norm(dim=-1)
    direction = positional_encoding(directions / norms[:, None], direction_frequencies)
    direction = direction[:, None].expand(-1, count, -1).reshape(-1, direction.shape[-1])
    return samples_points.reshape(-1, 3) * position_scale, direction, norms


def density_weights(raw: Tensor, depths: Tensor, norms: Tensor, noise: float,
                    generator: torch.Generator | None) -> Tensor:
    """NeRF's ``raw2outputs`` weights ``[R, S]``: ``alpha = 1 - exp(-ReLU(raw + noise) * delta * |d|)``, the last
    interval 1e10; Gaussian noise of std ``noise`` on the raw density only with a ``generator`` (training)."""
    if generator is not None and noise > 0:
        raw = raw + noise * torch.randn(raw.shape, generator=generator, device=raw.device, dtype=raw.dtype)
    return compositing_weights(density_opacity(F.relu(raw) * norms[:, None], depths))


class PerSceneNeRFHooks(FamilyHooks):
    """A per-scene NeRF's outputs are its coarse and fine fields' (for the message naming a NaN's maker)."""

    def output_owners(self, names: Mapping[str, str]) -> dict[str, str]:
        field = f"model {names.get('model', type(self.family).__name__)!r} (its coarse and fine fields)"
        return {"colour": field, "depth": field, "logits": field}


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
        field: ``mlp`` (NeRF's MLP above: ``width``, ``depth``, ``skip``, ``position_frequencies``) or ``grid``
            (``HashGridField``: the ``grid_*`` options; ``position_scale`` scales its positions too).
        grid_levels, grid_features, grid_table_log2, grid_base_resolution, grid_finest_resolution, grid_width: the
            hash grid's (``HashGridField``), read with ``field="grid"`` only.
        detach_branch: the branch reads the trunk features detached (its loss never shapes the geometry).
    """

    capabilities = Capabilities(generalizable=False, accepts_head=False, source_encoding=None, hooks=PerSceneNeRFHooks)

    def __init__(self, *, coarse_samples: int, fine_samples: int, width: int, depth: int, skip: int,
                 position_scale: float, position_frequencies: int, direction_frequencies: int, density_noise: float,
                 inverse_depth: bool, field: str = "mlp", grid_levels: int = 16, grid_features: int = 2,
                 grid_table_log2: int = 16, grid_base_resolution: float = 16.0,
                 grid_finest_resolution: float = 1024.0, grid_width: int = 64, detach_branch: bool = False) -> None:
        super().__init__()
        grid = dict(levels=grid_levels, features=grid_features, table_log2=grid_table_log2,
                    base_resolution=grid_base_resolution, finest_resolution=grid_finest_resolution, width=grid_width)
        check_field_options(coarse_samples=coarse_samples, fine_samples=fine_samples, width=width, depth=depth,
                            skip=skip, position_scale=position_scale, position_frequencies=position_frequencies,
                            direction_frequencies=direction_frequencies, density_noise=density_noise, field=field,
                            **({f"grid_{key}": value for key, value in grid.items()} if field == "grid" else {}))
        self.field_kind = field
        self.coarse_samples, self.fine_samples = int(coarse_samples), int(fine_samples)
        self.position_scale, self.density_noise = float(position_scale), float(density_noise)
        self.direction_frequencies = int(direction_frequencies)  # the position is encoded by each field
        self.inverse_depth = bool(inverse_depth)

        direction_dim = 3 * (1 + 2 * direction_frequencies)

        def make_field() -> NeRFField | HashGridField:
            if field == "grid":
                return HashGridField(**grid, direction_dim=direction_dim, branch=self.make_branch(grid_width),
                                     detach_branch=detach_branch)
            return NeRFField(width=width, depth=depth, skip=skip, position_frequencies=position_frequencies,
                             direction_dim=direction_dim, branch=self.make_branch(width), detach_branch=detach_branch)

        self.coarse = make_field()
        self.fine = make_field() if fine_samples else None

    # ---- what a subclass says ---------------------------------------------------------------------------------------

    def make_branch(self, width: int) -> nn.Module | None:
        """The branch of one field on its ``[N, width]`` trunk features (None: colour and depth only)."""
        return None

    def composite_branch(self, weights: Tensor, outputs: Tensor) -> Tensor:
        """The per-ray scores ``[R, X]`` of per-sample branch outputs ``[R, S, X]`` (label rendering)."""
        return composite(weights, outputs)

    # ---- what the model is ------------------------------------------------------------------------------------------

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """The scene's own field (``model.lr.field``); a hash grid's tables at ``model.lr.grid``."""
        if self.field_kind != "grid":
            return {"field": list(self.parameters())}
        tables = [table for field in (self.coarse, self.fine) if field is not None for table in field.grid_parameters()]
        return {"field": [p for p in self.parameters() if all(p is not table for table in tables)], "grid": tables}

    # ---- rendering ---------------------------------------------------------------------------------------------------

    def _pass(self, field: NeRFField | HashGridField, rays: RayBatch, samples: RaySamples, branch: bool, per_sample: bool,
              generator: torch.Generator | None) -> RenderedRays:
        count = samples.depths.shape[1]
        position, direction, norms = field_inputs(samples.points, rays.directions, count, self.position_scale,
                                                  self.direction_frequencies)
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
