"""The ``dice`` loss set: a built-in loss set's terms plus a soft Dice term on the head's logits.

The built-in terms are reached only through the public registry (``get_registry().build("loss", ...)``), never by
importing another plugin's modules, so any registered loss set can serve as the base.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch.nn.functional as F
from torch import Tensor

from gpnerf_core import ConfigError, LossInputs, LossSet, get_registry


@dataclass
class DiceLossConfig:
    """Options of the ``dice`` loss set (``+loss=dice loss.dice_weight=1.0``)."""

    name: str = "dice"
    """Registry name: the Hydra option ``loss/dice``."""
    base: str = "dgs"
    """Registered loss set whose terms are kept, with its default weights ('' for the Dice term alone)."""
    dice_weight: float = 0.5
    """Weight of the soft Dice term."""
    smooth: float = 1.0
    """Added to the Dice numerator and denominator: keeps the term finite and smooth for absent classes."""


def soft_dice(logits: Tensor, labels: Tensor, ignore_index: int, smooth: float) -> Tensor:
    """``1 -`` the soft Dice coefficient averaged over the K classes, on the labelled pixels.

    Args:
        logits: ``[N, K, H, W]``.
        labels: ``[N, H, W]`` int64 in ``[0, K)`` or ``ignore_index``.
    """
    classes = logits.shape[1]
    valid = labels != ignore_index
    if bool((labels[valid] >= classes).any()) or bool((labels[valid] < 0).any()):
        raise ConfigError(f"Dice got labels outside the head's {classes} classes (ignore_index={ignore_index})")
    mask = valid[:, None].to(logits.dtype)
    probabilities = logits.softmax(dim=1) * mask
    one_hot = F.one_hot(labels.where(valid, 0), classes).permute(0, 3, 1, 2).to(logits.dtype) * mask
    overlap = (probabilities * one_hot).sum(dim=(0, 2, 3))
    sizes = probabilities.sum(dim=(0, 2, 3)) + one_hot.sum(dim=(0, 2, 3))
    return 1.0 - ((2.0 * overlap + smooth) / (sizes + smooth)).mean()


class DiceLossSet(LossSet):
    """The ``base`` loss set's weighted terms and ``dice``: ``dice_weight * soft_dice(logits, labels)``.

    Args:
        base, dice_weight, smooth: see ``DiceLossConfig``.
    """

    needs_semantics = True  # the Dice term reads the head's logits

    def __init__(self, *, base: str, dice_weight: float, smooth: float) -> None:
        super().__init__()
        if not (math.isfinite(dice_weight) and dice_weight > 0):
            raise ConfigError(f"loss.dice_weight={dice_weight}: expected a finite weight > 0")
        if not (math.isfinite(smooth) and smooth > 0):
            raise ConfigError(f"loss.smooth={smooth}: expected a finite value > 0")
        if base == "dice":
            raise ConfigError("loss.base='dice' would include itself; name a built-in loss set such as dgs")
        self.base = get_registry().build("loss", {"name": base}) if base else None
        self.needs_sample_semantics = bool(self.base is not None and self.base.needs_sample_semantics)
        self.dice_weight = float(dice_weight)
        self.smooth = float(smooth)

    def forward(self, inputs: LossInputs) -> dict[str, Tensor]:
        terms = dict(self.base(inputs)) if self.base is not None else {}
        if inputs.logits is None or inputs.labels is None:
            raise ConfigError("loss term 'dice' needs head logits and labels; select a head (+head=<name>)")
        terms["dice"] = self.dice_weight * soft_dice(inputs.logits, inputs.labels, inputs.ignore_index, self.smooth)
        return terms
