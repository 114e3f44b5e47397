"""The ``dm_nerf`` loss set: DM-NeRF's losses for its object field (official ``networks/evaluator.py``
``ins_criterion``, ``networks/penalizer.py``, ``train_replica.py``), per pass (coarse and fine), all with weight 1:

- ``rgb``: the colour MSE;
- ``object``: the Hungarian-matched object loss on the step's rays: each slot's probability is the sigmoid of its
  composited logit (the empty slot dropped), GT instances and slots are paired on mean BCE + (1 - soft IoU), the loss is
  the matched pairs' BCE + the unmatched slots' mean probability + the matched pairs' (1 - soft IoU)
  (``matched_instance_loss``, shared with the instance head's loss set);
- ``empty``: the 3D emptiness penalty on each sample's own object logits, around the ray's rendered depth ``d``
  (detached): with ``G(x) = exp(-x^2 / (2 s^2)) / (0.4 sqrt(2 pi))`` (``s`` = ``loss.empty_sigma``, peak about 1), a
  sample in front of ``d - tolerance`` should be empty (BCE of all K + 1 sigmoids towards the one-hot empty slot,
  weighted by ``1 - G(t - d)``, normalised by ``(K + 1)`` x their count), a sample within ``+- tolerance`` should not
  (BCE pushing the empty slot to 0, weighted by ``G(t - d)``); samples behind ``d + tolerance`` get no term.

Distances here are in depth units (camera z, metres); DM-NeRF's are along its rays, whose directions it normalises the
same way for Replica's pinhole cameras up to the ray's length. ``loss.empty_after`` delays the penalty (0: from the
first step, as DM-NeRF; a short run's early depths are noise, so a warm-up is the deviation the docs name if used).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from gpnerf_core import ConfigError, ImageLossInputs, LossInputs, LossSet, Predicts, RenderedRays
from gpnerf_plugins.losses.instance import matched_instance_loss
from gpnerf_plugins.losses.terms import rgb_mse


@dataclass
class DMNeRFLossConfig:
    """DM-NeRF's loss: colour, the matched object loss and the emptiness penalty, per pass."""

    name: str = "dm_nerf"
    """Registry name of the loss set."""
    rgb_weight: float = 1.0
    """Weight of the colour MSE (coarse + fine)."""
    object_weight: float = 1.0
    """Weight of the Hungarian-matched object loss (coarse + fine)."""
    empty_weight: float = 1.0
    """Weight of the 3D emptiness penalty (coarse + fine; 0 = off, DM-NeRF's ``--penalize`` unset)."""
    tolerance: float = 0.05
    """Metres around the rendered depth where samples are the surface (DM-NeRF's ``tolerance``)."""
    empty_sigma: float = 0.05
    """Width of the Gaussian weighting of the penalty, metres (DM-NeRF's ``deta_w``)."""


def gaussian_weight(distance: Tensor, sigma: float) -> Tensor:
    """DM-NeRF's ``G(x) = exp(-x^2 / (2 sigma^2)) / (0.4 sqrt(2 pi))``: about 1 at the surface."""
    return torch.exp(-(distance**2) / (2 * sigma**2)) / (0.4 * math.sqrt(2 * math.pi))


def emptiness_penalty(sample_logits: Tensor, depths: Tensor, rendered_depth: Tensor, tolerance: float,
                      sigma: float) -> Tensor:
    """The 3D emptiness penalty of one pass (module docstring): ``[R, S, K + 1]`` per-sample object logits, ``[R, S]``
    sample depths, ``[R]`` rendered depth (detached here)."""
    offset = depths - rendered_depth.detach()[:, None]  # [R, S]: negative in front of the surface
    g = gaussian_weight(offset, sigma)
    in_front, at_surface = offset < -tolerance, offset.abs() <= tolerance
    outputs = sample_logits.shape[-1]
    zero = sample_logits.sum() * 0.0
    penalty = zero
    if bool(in_front.any()):
        empty = torch.zeros_like(sample_logits[in_front])
        empty[:, -1] = 1.0
        bce = F.binary_cross_entropy_with_logits(sample_logits[in_front], empty, reduction="none").sum(-1)
        penalty = penalty + (bce * (1.0 - g[in_front])).sum() / (outputs * int(in_front.sum()))
    if bool(at_surface.any()):
        void = sample_logits[at_surface][:, -1]
        bce = F.binary_cross_entropy_with_logits(void, torch.zeros_like(void), reduction="none")
        penalty = penalty + (bce * g[at_surface]).sum() / int(at_surface.sum())
    return penalty


class DMNeRFLossSet(LossSet):
    """Weighted terms ``rgb``, ``object`` and (unless its weight is 0) ``empty``, each summed over the passes.

    Args: the fields of ``DMNeRFLossConfig`` except ``name``.
    """

    needs_semantics = True
    needs_instances = True
    needs_labels = True
    head_predicts = Predicts.INSTANCES

    def __init__(self, rgb_weight: float = DMNeRFLossConfig.rgb_weight,
                 object_weight: float = DMNeRFLossConfig.object_weight,
                 empty_weight: float = DMNeRFLossConfig.empty_weight, tolerance: float = DMNeRFLossConfig.tolerance,
                 empty_sigma: float = DMNeRFLossConfig.empty_sigma) -> None:
        super().__init__()
        weights = {"rgb": rgb_weight, "object": object_weight, "empty": empty_weight}
        for term, weight in weights.items():
            if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not math.isfinite(weight) \
                    or weight < 0:
                raise ConfigError(f"loss.{term}_weight={weight!r}: expected a finite weight >= 0")
        for key, value in (("tolerance", tolerance), ("empty_sigma", empty_sigma)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                     and value > 0):
                raise ConfigError(f"loss.{key}={value!r}: expected metres > 0")
        if not any(weights.values()):
            raise ConfigError("every loss weight (rgb_weight, object_weight, empty_weight) is 0; nothing to train")
        self.weights = {term: float(weight) for term, weight in weights.items() if weight}
        self.tolerance, self.empty_sigma = float(tolerance), float(empty_sigma)
        self.needs_sample_semantics = "empty" in self.weights

    @staticmethod
    def _passes(inputs: LossInputs) -> list[RenderedRays]:
        return [p for p in (inputs.coarse, inputs.fine) if p is not None]

    def forward(self, inputs: LossInputs | ImageLossInputs) -> dict[str, Tensor]:
        if isinstance(inputs, ImageLossInputs):
            raise ConfigError("the dm_nerf loss set composites object logits along rays and penalises samples, and the "
                              "model renders whole images; use a loss set on images (+loss=image, +loss=instance)")
        terms = {"rgb": self._rgb, "object": self._object, "empty": self._empty}
        return {term: weight * terms[term](inputs) for term, weight in self.weights.items()}

    def _rgb(self, inputs: LossInputs) -> Tensor:
        return sum(rgb_mse(p.rgb, inputs.target_rgb) for p in self._passes(inputs))

    def _object(self, inputs: LossInputs) -> Tensor:
        if inputs.instances_at_rays is None:
            raise ConfigError("loss term 'object' needs the target's instance ids at the rays; the pipeline gave none")
        total = []
        for rendered in self._passes(inputs):
            if rendered.logits is None:
                raise ConfigError("loss term 'object' needs per-ray object logits; select model=dm_nerf")
            log_p = F.logsigmoid(rendered.logits.float())[:, :-1].T  # [K, R]: each slot's own sigmoid, empty dropped
            parts = matched_instance_loss(log_p, inputs.instances_at_rays, "model", "model.slots")
            total.append(parts["bce"] + parts["unmatched"] + parts["iou"])
        return sum(total)

    def _empty(self, inputs: LossInputs) -> Tensor:
        total = []
        for rendered in self._passes(inputs):
            if rendered.sample_semantic is None:
                raise ConfigError("loss term 'empty' needs per-sample object logits; select model=dm_nerf")
            total.append(emptiness_penalty(rendered.sample_semantic, rendered.samples.depths, rendered.depth,
                                           self.tolerance, self.empty_sigma))
        return sum(total)
