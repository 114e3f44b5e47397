"""Adaptive density control as strategies (gsplat's ``Strategy``): when Gaussians are cloned, split and pruned.

A strategy holds thresholds and a schedule and is driven by the family's hooks at two points of a training step, with
gsplat's arguments: ``step_pre_backward(params, optimizer, state, step, info)`` before the backward pass (the projected
centres keep their gradient; ``TrainingPhase.BEFORE_BACKWARD``) and ``step_post_backward(params, optimizer, state,
step, info)`` between the backward pass and the optimizer step (3D Gaussian splatting's order; ``AFTER_BACKWARD``),
where ``params`` are the ``GaussianParameters``, ``state`` their
row state (the strategy's per-Gaussian statistics, ``initialize_state``), ``step`` the training step counted from 0 and
``info`` what the rasterizer reported per rendered view (``ViewInfo``: projected centres, footprint radii, image size).
Every row change goes through ``GaussianParameters.set_rows``, so the optimizer's moments and the statistics follow the
rows (``append_rows``, ``keep_rows``, ``split_rows``, ``reset_opacity``: the operations a new strategy is made of).

- ``DefaultStrategy``: the official schedule (Kerbl et al. 2023, section 5; ``GaussianModel.add_densification_stats``,
  ``densify_and_clone``, ``densify_and_split``, ``densify_and_prune``, ``reset_opacity``). Each Gaussian seen in a view
  adds the norm of its view-space positional gradient (the projected centre's, in normalised device coordinates: the
  official rasterizer's ``dL_dmean2D`` is per pixel times ``W / 2`` and ``H / 2``) and counts one view; its largest
  footprint radius is kept. Every ``densify_every`` steps from ``densify_from`` to ``densify_until``, Gaussians whose mean
  gradient reaches ``grad_threshold`` are cloned (largest scale at most ``percent_dense`` of the extent) or split in two
  (two samples of the Gaussian, scales / 1.6, the originals removed); then Gaussians below ``prune_opacity``, and after
  the first opacity reset those whose footprint radius passed ``prune_screen_radius`` pixels or whose largest scale
  passed ``prune_world_scale`` of the extent, are removed; every ``opacity_reset_every`` steps each opacity is capped
  at 0.01. ``max_gaussians`` is a safety cap on growth (the official code has none): candidates past it are dropped,
  the highest rows first, and the cap is said once.
- ``BudgetedStrategy``: the same schedule under a budget the count never exceeds: the number of Gaussians allowed
  rises linearly from the start to ``budget`` over the densification window, and the Gaussians with the largest mean
  gradients grow first (the score-ranked, budget-scheduled growth of Taming 3DGS, Mallick et al. 2024, with the
  gradient as its score).

One departure from the official code: its ``densification_postfix`` zeroes every footprint radius when it appends
Gaussians, before ``densify_and_prune`` tests them, so its screen-size pruning fires only in a densification that
cloned and split nothing; here the radii gathered since the last densification are tested, as the paper describes.
The schedules' step numbers are the official ones for ``schedule_steps`` steps; ``scaled(total_steps)`` gives them for
a run of another length (gsplat's ``steps_scaler``), except that opacity resets scaled closer than
``MIN_RESET_INTERVAL`` steps apart are dropped for the run (``schedule_note`` says so; the family prints it once).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from gpnerf_core.errors import ConfigError
from gpnerf_core.geometry.gaussians.parameters import GaussianParameters
from gpnerf_core.geometry.gaussians.rows import resize_parameter

OPACITY_RESET = 0.01
"""Every opacity is capped at this by a reset (3DGS's ``reset_opacity``)."""
SPLIT_INTO = 2
"""A split Gaussian becomes this many (3DGS: N = 2), each with its scales divided by 0.8 N."""
STATISTICS = ("gradient_sum", "gradient_count", "max_radius")
"""The per-Gaussian statistics of the strategies here (``GaussianParameters`` row state)."""

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ViewInfo:
    """What the rasterizer reports of one rendered view that density control reads (gsplat's ``info``).

    Attributes:
        means2d: ``[G, 2]`` projected centres in pixels (``Rasterized.means2d``), whose gradient ``step_pre_backward``
            retains.
        radii: ``[G]`` footprint radii in pixels, 0 for a Gaussian the view does not see.
        height, width: the rendered image's size, pixels.
    """

    means2d: Tensor
    radii: Tensor
    height: int
    width: int


MIN_RESET_INTERVAL = 50
"""Fewest steps between two opacity resets a scaled schedule keeps: below it (a run under a tenth of 3DGS's 30k-step
schedule at 1/60 of its length, say) a run resets no opacity (``DefaultStrategy.scaled``). Each reset caps every
opacity at 0.01, and the official schedule leaves 3000 steps to recover; a run of 20 steps would reset at every
step of its first half and render near-black."""


def scaled_step(official: int, total_steps: int, schedule_steps: int) -> int:
    """An official schedule's step number for a run of ``total_steps`` (at least 1)."""
    return max(1, round(official * total_steps / schedule_steps))


# ---- the operations -------------------------------------------------------------------------------------------------


def append_rows(params: GaussianParameters, optimizer: torch.optim.Optimizer, new: dict[str, Tensor]) -> None:
    """Add the rows ``new`` (every per-Gaussian parameter) after the existing ones, with zero moments and statistics."""
    params.set_rows({name: torch.cat([tensor, new[name]]) for name, tensor in params.rows().items()}, optimizer)


def keep_rows(params: GaussianParameters, optimizer: torch.optim.Optimizer, keep: Tensor) -> None:
    """Keep the rows where ``keep`` ``[G]`` is True; their moments and statistics go with them."""
    params.set_rows({name: tensor[keep] for name, tensor in params.rows().items()}, optimizer, kept=keep)


def split_rows(params: GaussianParameters, chosen: Tensor, into: int = SPLIT_INTO) -> dict[str, Tensor]:
    """``into`` new rows per chosen Gaussian: centres sampled from it (the global random stream, which a checkpoint
    keeps), scales / (0.8 x ``into``), every other value copied. The caller appends them and removes the originals."""
    rows = {name: tensor[chosen].repeat(into, *([1] * (tensor.ndim - 1))) for name, tensor in params.rows().items()}
    scales = rows["log_scales"].exp()
    offsets = torch.normal(torch.zeros_like(scales), scales)
    rotation = rotation_matrices(rows["rotations"])
    rows["means"] = torch.bmm(rotation, offsets[..., None])[..., 0] + rows["means"]
    rows["log_scales"] = torch.log(scales / (0.8 * into))
    return rows


def reset_opacity(params: GaussianParameters, optimizer: torch.optim.Optimizer, value: float = OPACITY_RESET) -> None:
    """Cap every opacity at ``value``; the opacities' moments start again (3DGS's ``reset_opacity``)."""
    with torch.no_grad():
        capped = torch.sigmoid(params.opacity_logits).clamp_max(value)
        fresh = torch.zeros(0, dtype=torch.long, device=capped.device)
        params.opacity_logits = resize_parameter(optimizer, params.opacity_logits, torch.logit(capped), fresh)


def rotation_matrices(quaternions: Tensor) -> Tensor:
    """``[N, 3, 3]`` of ``(w, x, y, z)`` quaternions of any norm (3DGS's ``build_rotation``)."""
    w, x, y, z = (quaternions / quaternions.norm(dim=-1, keepdim=True).clamp_min(1e-12)).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


# ---- strategies -----------------------------------------------------------------------------------------------------


class DensityStrategy:
    """The protocol of a density strategy (gsplat's ``Strategy``): a subclass overrides the steps it acts at."""

    def check_sanity(self, params: GaussianParameters, optimizer: torch.optim.Optimizer) -> None:
        """Every per-Gaussian parameter is stepped by ``optimizer``, in one group each and no other: a ConfigError
        naming the parameter otherwise (rows added or removed would not reach the optimizer)."""
        members = {id(p): group.get("name", "?") for group in optimizer.param_groups for p in group["params"]}
        for name, parameter in params.rows().items():
            if id(parameter) not in members:
                raise ConfigError(f"Gaussian parameter {name!r} is not in the optimizer: density control cannot move "
                                  "its moments with its rows (a family's parameter_groups() must list every row)")
            holders = [g for g in optimizer.param_groups if any(p is parameter for p in g["params"])]
            if len(holders) != 1 or len(holders[0]["params"]) != 1:
                raise ConfigError(f"Gaussian parameter {name!r} shares an optimizer group: density control resizes "
                                  "each in a group of its own")

    def initialize_state(self, params: GaussianParameters) -> None:
        """Register the per-Gaussian statistics this strategy keeps (``GaussianParameters.register_row_state``)."""

    def schedule_note(self, total_steps: int) -> str | None:
        """One line on how a run of ``total_steps`` departs from the strategy's schedule (the family prints it once
        when training starts), or None."""
        return None

    def step_pre_backward(self, params: GaussianParameters, optimizer: torch.optim.Optimizer,
                          state: dict[str, Tensor], step: int, info: Sequence[ViewInfo]) -> None:
        """Before the backward pass: keep what it must fill."""

    def step_post_backward(self, params: GaussianParameters, optimizer: torch.optim.Optimizer,
                           state: dict[str, Tensor], step: int, info: Sequence[ViewInfo]) -> None:
        """Between the backward pass and the optimizer step: statistics and density changes."""


@dataclass(frozen=True)
class DefaultStrategy(DensityStrategy):
    """3D Gaussian splatting's density control on its official schedule (the module docstring); step numbers are the
    official ones for ``schedule_steps`` steps (``scaled``)."""

    grad_threshold: float = 2.0e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    prune_screen_radius: float = 20.0
    prune_world_scale: float = 0.1
    densify_from: int = 500
    densify_until: int = 15000
    densify_every: int = 100
    opacity_reset_every: int = 3000
    max_gaussians: int = 1_000_000_000
    schedule_steps: int = 30000

    def scaled(self, total_steps: int) -> "DefaultStrategy":
        """The same strategy for a run of ``total_steps`` steps: each step number scaled by ``total_steps /
        schedule_steps`` (at least 1); the opacity resets dropped when their scaled interval falls below
        ``MIN_RESET_INTERVAL`` (``resets_dropped``; ``schedule_note`` says why)."""
        steps = {name: scaled_step(getattr(self, name), total_steps, self.schedule_steps)
                 for name in ("densify_from", "densify_until", "densify_every", "opacity_reset_every")}
        if self.resets_dropped(total_steps):
            steps["opacity_reset_every"] = total_steps + 1  # never within the run (nor the pruning gated on it)
        return dataclasses.replace(self, **steps, schedule_steps=total_steps)

    def resets_dropped(self, total_steps: int) -> bool:
        """Whether a run of ``total_steps`` drops the opacity resets: scaling shrank their interval below
        ``MIN_RESET_INTERVAL`` steps (an interval configured that short, unscaled, is kept)."""
        interval = scaled_step(self.opacity_reset_every, total_steps, self.schedule_steps)
        return interval < min(MIN_RESET_INTERVAL, self.opacity_reset_every)

    def schedule_note(self, total_steps: int) -> str | None:
        """One line saying that, and why, a run of ``total_steps`` resets no opacity; None when it keeps the resets."""
        if not self.resets_dropped(total_steps):
            return None
        interval = scaled_step(self.opacity_reset_every, total_steps, self.schedule_steps)
        keeps = next(steps for steps in range(total_steps + 1, 100 * self.schedule_steps + 2)
                     if not self.resets_dropped(steps))
        return (f"model.opacity_reset_every={self.opacity_reset_every} of a {self.schedule_steps}-step schedule "
                f"(model.schedule_steps) scaled to {total_steps} steps would cap every opacity at 0.01 every "
                f"{interval} step(s), under {MIN_RESET_INTERVAL}: too often for the Gaussians to recover (the render "
                f"turns near-black), so this run resets no opacity and, as 3DGS before its first reset, prunes none "
                f"by screen or world size; runs of {keeps} steps or more keep the resets")

    def initialize_state(self, params: GaussianParameters) -> None:
        for name in STATISTICS:
            params.register_row_state(name)

    def step_pre_backward(self, params: GaussianParameters, optimizer: torch.optim.Optimizer,
                          state: dict[str, Tensor], step: int, info: Sequence[ViewInfo]) -> None:
        for view in info:
            if view.means2d.requires_grad:
                view.means2d.retain_grad()

    def step_post_backward(self, params: GaussianParameters, optimizer: torch.optim.Optimizer,
                           state: dict[str, Tensor], step: int, info: Sequence[ViewInfo]) -> None:
        iteration = step + 1  # the official loop counts iterations from 1
        if iteration >= self.densify_until:
            return
        for view in info:
            add_statistics(params, state, view)
        if iteration > self.densify_from and iteration % self.densify_every == 0:
            self.densify_and_prune(params, optimizer, iteration, prune_large=iteration > self.opacity_reset_every)
        if iteration % self.opacity_reset_every == 0:
            reset_opacity(params, optimizer)

    def grow(self, params: GaussianParameters, candidates: Tensor, iteration: int) -> Tensor:
        """The candidates ``[G]`` that grow this time: within ``max_gaussians`` (the highest rows dropped first)."""
        return _within(candidates, params, self.max_gaussians - params.size, self.max_gaussians)

    def densify_and_prune(self, params: GaussianParameters, optimizer: torch.optim.Optimizer, iteration: int, *,
                          prune_large: bool) -> tuple[int, int]:
        """Clone, split, then prune (the module docstring). Returns ``(added, removed)``."""
        with torch.no_grad():
            state = params.row_state()
            before = params.size
            mean_gradient = torch.nan_to_num(state["gradient_sum"] / state["gradient_count"], nan=0.0)
            extent = float(params.extent)
            chosen = self.grow(params, mean_gradient >= self.grad_threshold, iteration)
            largest = params.log_scales.exp().max(dim=-1).values
            clone = chosen & (largest <= self.percent_dense * extent)
            split = chosen & (largest > self.percent_dense * extent)
            if bool(clone.any()):
                append_rows(params, optimizer, {name: tensor[clone] for name, tensor in params.rows().items()})
                split = torch.cat([split, split.new_zeros(int(clone.sum()))])
            if bool(split.any()):
                append_rows(params, optimizer, split_rows(params, split))
                keep = ~torch.cat([split, split.new_zeros(SPLIT_INTO * int(split.sum()))])
                keep_rows(params, optimizer, keep)
            state = params.row_state()
            prune = torch.sigmoid(params.opacity_logits) < self.prune_opacity
            if prune_large:
                prune |= state["max_radius"] > self.prune_screen_radius
                prune |= params.log_scales.exp().max(dim=-1).values > self.prune_world_scale * extent
            if params.size and bool(prune.all()):
                raise ConfigError(self.all_pruned_message(params, iteration, prune_large))
            added = params.size - before
            if bool(prune.any()):
                keep_rows(params, optimizer, ~prune)
            for tensor in params.row_state().values():
                tensor.zero_()
            return max(added, 0), int(prune.sum())


    def all_pruned_message(self, params: GaussianParameters, iteration: int, prune_large: bool) -> str:
        """Why pruning at ``iteration`` would remove every one of the ``params``' Gaussians: each rule's count and its
        key, and what to change."""
        opacities = torch.sigmoid(params.opacity_logits)
        causes = [f"{int((opacities < self.prune_opacity).sum())} with opacity below model.prune_opacity="
                  f"{self.prune_opacity:g} (the largest opacity is {float(opacities.max()):.3g})"]
        if prune_large:
            extent = float(params.extent)
            radius = params.row_state()["max_radius"]
            largest = params.log_scales.exp().max(dim=-1).values
            causes.append(f"{int((radius > self.prune_screen_radius).sum())} wider than model.prune_screen_radius="
                          f"{self.prune_screen_radius:g} px")
            causes.append(f"{int((largest > self.prune_world_scale * extent).sum())} larger than "
                          f"model.prune_world_scale={self.prune_world_scale:g} x the cameras' extent {extent:.3g} m")
        return (f"step {iteration - 1}: density control would prune every one of the {params.size} Gaussians "
                f"({'; '.join(causes)}), leaving the model with no Gaussians; expected thresholds the Gaussians meet: "
                "lower model.prune_opacity (3DGS: 0.005) or raise the others, or check that the scene's points and "
                "cameras share one world")


@dataclass(frozen=True)
class BudgetedStrategy(DefaultStrategy):
    """``DefaultStrategy`` under a budget of ``budget`` Gaussians that the count never exceeds (the module docstring):
    at a densification at iteration ``i`` the count may reach ``start + (budget - start) * progress(i)``, with
    ``progress`` rising linearly from 0 at ``densify_from`` to 1 at ``densify_until``, and the Gaussians with the
    largest mean gradients grow first. A start above the budget is refused (``check_start``)."""

    budget: int = 1_000_000

    def check_start(self, count: int) -> None:
        """A ConfigError when a start of ``count`` Gaussians is already over the budget."""
        if count > self.budget:
            raise ConfigError(f"the Gaussians start with {count} rows, above the budget of {self.budget} "
                              "(model.max_gaussians): raise the budget or start from fewer points (model.init_points)")

    def initialize_state(self, params: GaussianParameters) -> None:
        super().initialize_state(params)
        if not hasattr(params, "budget_start"):  # the count when growth began (0: not yet); a checkpoint keeps it
            params.register_buffer("budget_start", torch.zeros((), dtype=torch.long, device=params.means.device))

    def allowed(self, start: int, iteration: int) -> int:
        """How many Gaussians the budget allows at ``iteration`` when growth began at ``start``."""
        span = max(1, self.densify_until - self.densify_from)
        progress = min(1.0, max(0.0, (iteration - self.densify_from) / span))
        return min(self.budget, start + int((self.budget - start) * progress))

    def grow(self, params: GaussianParameters, candidates: Tensor, iteration: int) -> Tensor:
        """The candidates with the largest mean gradients, as many as the budget allows now (a split adds one net)."""
        if int(params.budget_start) == 0:
            params.budget_start.fill_(params.size)
        room = self.allowed(int(params.budget_start), iteration) - params.size
        if int(candidates.sum()) <= room:
            return candidates
        chosen = torch.zeros_like(candidates)
        if room > 0:
            state = params.row_state()
            score = torch.nan_to_num(state["gradient_sum"] / state["gradient_count"], nan=0.0)
            ranked = torch.where(candidates, score, torch.full_like(score, -1.0)).argsort(descending=True, stable=True)
            chosen[ranked[:room]] = True
        return chosen


def add_statistics(params: GaussianParameters, state: dict[str, Tensor], view: ViewInfo) -> None:
    """Accumulate one rendered view's statistics: the view-space gradient norm (in NDC units) and a count for each
    Gaussian it sees (``radii`` > 0), and its largest footprint radius."""
    means2d, radii = view.means2d, view.radii
    seen = radii > 0
    if means2d.grad is None or not bool(seen.any()):
        return
    gradient = means2d.grad[seen] * means2d.grad.new_tensor([view.width / 2.0, view.height / 2.0])
    state["max_radius"][seen] = torch.maximum(state["max_radius"][seen], radii[seen].to(state["max_radius"].dtype))
    state["gradient_sum"][seen] += gradient.norm(dim=-1)
    state["gradient_count"][seen] += 1


def _within(candidates: Tensor, params: GaussianParameters, room: int, cap: int) -> Tensor:
    """At most ``room`` new Gaussians: a small candidate is cloned (one more), a large one split (one more net); past
    the room the highest rows are dropped first, and the cap is said once per parameters."""
    wanted = int(candidates.sum())
    if wanted <= room:
        return candidates
    if not getattr(params, "_cap_said", False):
        log.warning("model.max_gaussians=%d reached: densification adds no more Gaussians", cap)
        params._cap_said = True
    if room <= 0:
        return torch.zeros_like(candidates)
    return candidates & (torch.cumsum(candidates.long(), dim=0) <= room)
