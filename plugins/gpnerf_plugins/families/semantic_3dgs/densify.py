"""3D Gaussian splatting's adaptive density control (Kerbl et al. 2023, section 5; official ``GaussianModel``
``add_densification_stats``, ``densify_and_clone``, ``densify_and_split``, ``densify_and_prune``, ``reset_opacity``).

Between a step's backward pass and its optimizer step, each Gaussian seen in the step's views adds the norm of its
view-space positional gradient (the projected centre's, in normalised device coordinates: the official rasterizer's
``dL_dmean2D`` is per pixel times ``W / 2`` and ``H / 2``) and counts one view; its largest footprint radius is kept.
Every ``densify_every`` steps, Gaussians whose mean gradient reaches the threshold are cloned (small: largest scale at
most ``percent_dense`` of the extent) or split in two (large: two samples of the Gaussian, scales / 1.6), the split
originals removed; then Gaussians below ``prune_opacity``, and after the first opacity reset those whose footprint
radius passed ``prune_screen_radius`` pixels or whose largest scale passed ``prune_world_scale`` of the extent, are
removed. The Adam moments follow (``GaussianField.set_rows``).

One departure: the official ``densification_postfix`` zeroes every footprint radius when it appends Gaussians, before
``densify_and_prune`` tests them, so its screen-size pruning fires only in a densification that cloned and split
nothing; here the radii gathered since the last densification are tested, as the paper describes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import Tensor

from gpnerf_core import resize_parameter
from gpnerf_plugins.families.semantic_3dgs.field import GaussianField

OPACITY_RESET = 0.01
"""Every opacity is capped at this by a reset (3DGS's ``reset_opacity``)."""
SPLIT_INTO = 2
"""A split Gaussian becomes this many (3DGS: N = 2), each with its scales divided by 0.8 N."""

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DensityControl:
    """The thresholds of adaptive density control (``Semantic3DGSConfig``'s fields of the same names)."""

    grad_threshold: float
    percent_dense: float
    prune_opacity: float
    prune_screen_radius: float
    prune_world_scale: float
    max_gaussians: int


def add_statistics(field: GaussianField, means2d: Tensor, radii: Tensor, height: int, width: int) -> None:
    """Accumulate one rendered view's statistics: ``means2d`` ``[G, 2]`` projected centres (pixels) whose ``.grad``
    the backward pass filled, ``radii`` ``[G]`` footprint radii (0: not seen)."""
    seen = radii > 0
    if means2d.grad is None or not bool(seen.any()):
        return
    gradient = means2d.grad[seen] * means2d.grad.new_tensor([width / 2.0, height / 2.0])
    field.max_radius[seen] = torch.maximum(field.max_radius[seen], radii[seen].to(field.max_radius.dtype))
    field.gradient_sum[seen] += gradient.norm(dim=-1)
    field.gradient_count[seen] += 1


def densify_and_prune(field: GaussianField, optimizer: torch.optim.Optimizer, control: DensityControl,
                      prune_large: bool, warned: list[bool]) -> tuple[int, int]:
    """Clone, split, then prune (the module docstring); ``prune_large``: also by screen and world size (after the
    first opacity reset). ``warned`` (a one-element list) records that the ``max_gaussians`` cap was said once.
    Returns ``(added, removed)``."""
    with torch.no_grad():
        before = field.size
        mean_gradient = torch.nan_to_num(field.gradient_sum / field.gradient_count, nan=0.0)
        extent = float(field.extent)
        room = control.max_gaussians - field.size
        chosen = mean_gradient >= control.grad_threshold
        largest = field.log_scales.exp().max(dim=-1).values
        clone = chosen & (largest <= control.percent_dense * extent)
        split = chosen & (largest > control.percent_dense * extent)
        clone, split = _within(clone, split, room, warned, control.max_gaussians)
        if bool(clone.any()):
            _append(field, optimizer, {name: tensor[clone] for name, tensor in field.rows().items()})
            split = torch.cat([split, split.new_zeros(int(clone.sum()))])
        if bool(split.any()):
            _append(field, optimizer, _split_rows(field, split))
            keep = ~torch.cat([split, split.new_zeros(SPLIT_INTO * int(split.sum()))])
            _keep(field, optimizer, keep)
        opacity = torch.sigmoid(field.opacity_logits)
        prune = opacity < control.prune_opacity
        if prune_large:
            prune |= field.max_radius > control.prune_screen_radius
            prune |= field.log_scales.exp().max(dim=-1).values > control.prune_world_scale * extent
        added = field.size - before
        if bool(prune.any()):
            _keep(field, optimizer, ~prune)
        field.reset_statistics()
        return max(added, 0), int(prune.sum())


def reset_opacity(field: GaussianField, optimizer: torch.optim.Optimizer) -> None:
    """Cap every opacity at ``OPACITY_RESET``; the opacities' moments start again (3DGS's ``reset_opacity``)."""
    with torch.no_grad():
        capped = torch.sigmoid(field.opacity_logits).clamp_max(OPACITY_RESET)
        fresh = torch.zeros(0, dtype=torch.long, device=capped.device)
        field.opacity_logits = resize_parameter(optimizer, field.opacity_logits, torch.logit(capped), fresh)


def _within(clone: Tensor, split: Tensor, room: int, warned: list[bool], cap: int) -> tuple[Tensor, Tensor]:
    """At most ``room`` new Gaussians: a clone adds one, a split adds one net (two for one); the highest-index ones
    are dropped first, and the cap is said once."""
    wanted = int(clone.sum()) + int(split.sum()) * (SPLIT_INTO - 1)
    if wanted <= room:
        return clone, split
    if not warned[0]:
        log.warning("model.max_gaussians=%d reached: densification adds no more Gaussians", cap)
        warned[0] = True
    if room <= 0:
        return torch.zeros_like(clone), torch.zeros_like(split)
    order = torch.cumsum(clone.long() + split.long() * (SPLIT_INTO - 1), dim=0)
    allowed = order <= room
    return clone & allowed, split & allowed


def _split_rows(field: GaussianField, split: Tensor) -> dict[str, Tensor]:
    """``SPLIT_INTO`` new Gaussians per split one: centres sampled from it (the global random stream, which a
    checkpoint keeps), scales / (0.8 x ``SPLIT_INTO``), the rest copied."""
    rows = {name: tensor[split].repeat(SPLIT_INTO, *([1] * (tensor.ndim - 1))) for name, tensor in field.rows().items()}
    scales = rows["log_scales"].exp()
    offsets = torch.normal(torch.zeros_like(scales), scales)
    rotation = _rotation_matrices(rows["rotations"])
    rows["means"] = torch.bmm(rotation, offsets[..., None])[..., 0] + rows["means"]
    rows["log_scales"] = torch.log(scales / (0.8 * SPLIT_INTO))
    return rows


def _append(field: GaussianField, optimizer: torch.optim.Optimizer, new: dict[str, Tensor]) -> None:
    field.set_rows({name: torch.cat([tensor, new[name]]) for name, tensor in field.rows().items()}, optimizer)


def _keep(field: GaussianField, optimizer: torch.optim.Optimizer, keep: Tensor) -> None:
    field.set_rows({name: tensor[keep] for name, tensor in field.rows().items()}, optimizer, kept=keep)


def _rotation_matrices(quaternions: Tensor) -> Tensor:
    """``[N, 3, 3]`` of ``(w, x, y, z)`` quaternions of any norm (3DGS's ``build_rotation``)."""
    w, x, y, z = (quaternions / quaternions.norm(dim=-1, keepdim=True).clamp_min(1e-12)).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


