"""The ``instance`` loss set: colour, the Hungarian-matched instance loss, optional semantic distillation.

The instance term follows the reference's ``ins_criterion`` (REFERENCE.md §1(c)): the head's ``slots + 1`` logits go
through a softmax and the last ("no instance") channel is dropped; every id in the target frame is an instance,
background included; GT masks and slots are matched by Hungarian matching on mean BCE + (1 - soft IoU), and the loss
is the matched pairs' mean BCE + the unmatched slots' mean probability + the matched pairs' mean (1 - soft IoU).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from gpnerf_core import ConfigError, ImageLossInputs, LossInputs, Predicts, hungarian, instance_masks
from gpnerf_plugins.losses.sets import LossSetConfig, WeightedLossSet

LOG_ONE_MINUS_FLOOR = 1e-7
"""log(1 - p) is taken at p <= 1 - this (the reference clamps p itself into [1e-6, 1 - 1e-6])."""


@dataclass
class InstanceLossConfig(LossSetConfig):
    """Colour + Hungarian instance loss (GP-NeRF's instance setting), with S.D available."""

    name: str = "instance"
    """Registry name of the loss set."""
    instance_weight: float = 1.0
    """Weight of the Hungarian-matched instance loss."""
    ce_weight: float = 0.0
    """Cross-entropy needs class logits; an instance head has none (must stay 0)."""
    sd_weight: float = 0.25
    """Weight of the 2D semantic distillation (rendered feature vs teacher), as in the main recipe."""
    dgs_weight: float = 0.0
    """Weight of the depth-guided distillation (off)."""


def hungarian_instance_loss(logits: Tensor, instance_ids: Tensor) -> dict[str, Tensor]:
    """The three parts of the instance loss of one image.

    Args:
        logits: ``[K + 1, H, W]`` head output (K slots + "no instance"), softmax over the channels.
        instance_ids: ``[H, W]`` integer GT ids; each id present is one instance.

    Returns:
        ``{"bce", "unmatched", "iou"}`` scalars (their sum is the loss); ``unmatched`` is 0 when every slot is matched.

    Raises:
        ConfigError: more GT instances than slots.
    """
    if logits.dim() != 3 or instance_ids.shape != logits.shape[1:]:
        raise ConfigError(
            f"instance loss got logits {tuple(logits.shape)} and instance ids {tuple(instance_ids.shape)}; "
            "expected [K + 1, H, W] and [H, W]"
        )
    # log p from log_softmax, never from a clamped p: a clamp has no gradient, and a head whose slots saturate (one
    # slot near 1 everywhere, the others near 0) would then never recover.
    log_p = torch.log_softmax(logits.float(), dim=0)[:-1]
    return matched_instance_loss(log_p.reshape(log_p.shape[0], -1), instance_ids.reshape(-1), "head", "head.slots")


def matched_instance_loss(log_p: Tensor, instance_ids: Tensor, owner: str, slots_key: str) -> dict[str, Tensor]:
    """The Hungarian-matched instance loss on ``N`` pixels or rays (the reference's and DM-NeRF's ``ins_criterion``).

    Args:
        log_p: ``[K, N]`` log-probability of each of K slots at each pixel (the empty slot already dropped: a softmax's
            or, for DM-NeRF, each slot's own sigmoid).
        instance_ids: ``[N]`` integer GT ids; each id present is one instance.
        owner, slots_key: what has the slots and the option that sets K, named when there are more instances than
            slots.

    Returns:
        ``{"bce", "unmatched", "iou"}``: the matched pairs' mean BCE, the unmatched slots' mean probability (0 when every
        slot is matched) and the matched pairs' mean (1 - soft IoU); GT masks and slots are paired by Hungarian matching
        on mean BCE + (1 - soft IoU).
    """
    slots = log_p.shape[0]
    _, gt = instance_masks(instance_ids)
    if gt.shape[0] > slots:
        raise ConfigError(
            f"a target frame has {gt.shape[0]} instance ids (background included) but the {owner} has {slots} slots; "
            f"set {slots_key} >= {gt.shape[0]}"
        )
    log_not_p = torch.log(-torch.expm1(log_p.clamp(max=-LOG_ONE_MINUS_FLOOR)))
    probabilities = log_p.exp()
    target = gt.to(probabilities.dtype)
    pixels = target.shape[1]
    # bce[g, k] = mean over pixels of BCE(slot k, mask g), as two matrix products.
    bce = -(target @ log_p.T + (1.0 - target) @ log_not_p.T) / pixels
    inter = target @ probabilities.T
    union = target.sum(1, keepdim=True) + probabilities.sum(1)[None] - inter
    soft_iou = inter / union.clamp(min=LOG_ONE_MINUS_FLOOR)
    rows, cols = hungarian((bce + 1.0 - soft_iou).detach().cpu().numpy())
    rows_t = torch.as_tensor(rows, device=log_p.device)
    cols_t = torch.as_tensor(cols, device=log_p.device)
    unmatched = torch.ones(slots, dtype=torch.bool, device=log_p.device)
    unmatched[cols_t] = False
    zero = probabilities.sum() * 0.0
    return {
        "bce": bce[rows_t, cols_t].mean(),
        "unmatched": probabilities[unmatched].mean() if unmatched.any() else zero,
        "iou": (1.0 - soft_iou[rows_t, cols_t]).mean(),
    }


class InstanceLossSet(WeightedLossSet):
    """Weighted terms ``rgb``, ``instance``, and ``sd`` / ``dgs`` when their weight is non-zero.

    Args: the fields of ``InstanceLossConfig`` except ``name``.
    """

    needs_instances = True
    head_predicts = Predicts.INSTANCES  # declared on the class: checked against the model before the options are

    def __init__(self, instance_weight: float = InstanceLossConfig.instance_weight, **options: float | bool | str):
        if float(options.get("ce_weight", 0.0)) != 0.0:
            raise ConfigError(
                f"loss.ce_weight={options['ce_weight']}: the instance loss set's head predicts instance slots, not "
                "classes; expected 0 (a weight an experiment sets for its own loss set stays when loss= replaces the "
                "set: set loss.ce_weight=0, or leave the experiment out)"
            )
        options.setdefault("sd_weight", InstanceLossConfig.sd_weight)
        options.setdefault("dgs_weight", InstanceLossConfig.dgs_weight)
        options["ce_weight"] = 0.0
        super().__init__(**options, extra_weights={"instance": instance_weight})
        self.needs_semantics = True
        self.needs_labels = True  # the instance term reads the target's instance ids
        self.head_predicts = Predicts.INSTANCES

    @staticmethod
    def _instance(inputs: LossInputs | ImageLossInputs) -> Tensor:
        """On the head's logits of the whole target (a ray family's decoded map, or an image family's)."""
        whole = isinstance(inputs, ImageLossInputs)
        logits = inputs.output.logits if whole else inputs.logits
        if logits is None:
            raise ConfigError("loss term 'instance' needs head logits; select an instance head (+head=instance)")
        if inputs.instances is None:
            raise ConfigError("loss term 'instance' needs the target's instance ids; the pipeline gave none")
        parts = hungarian_instance_loss(logits[0], inputs.instances if whole else inputs.instances[0])
        return parts["bce"] + parts["unmatched"] + parts["iou"]
