"""Assigning ground-truth boxes to anchors and proposals, and sampling a balanced minibatch of them (torchvision's
``Matcher`` and ``BalancedPositiveNegativeSampler``)."""

from __future__ import annotations

import torch
from torch import Tensor

BELOW_LOW = -1
"""A prediction whose best IoU is below the low threshold: background."""
BETWEEN = -2
"""A prediction whose best IoU is between the thresholds: ignored."""


def match(iou: Tensor, high: float, low: float, allow_low_quality: bool) -> Tensor:
    """Each prediction's ground truth.

    Args:
        iou: ``[G, N]`` IoU of every ground-truth box with every prediction (G >= 1).
        high, low: IoU >= ``high`` matches; < ``low`` is ``BELOW_LOW``; in between is ``BETWEEN``.
        allow_low_quality: also match, to each ground truth, the predictions of its highest IoU (Faster R-CNN's
            RPN rule, so every ground truth has an anchor).

    Returns:
        ``[N]`` int64: the matched ground truth's index, or ``BELOW_LOW`` / ``BETWEEN``.
    """
    values, matches = iou.max(dim=0)
    original = matches.clone()
    matches[values < low] = BELOW_LOW
    matches[(values >= low) & (values < high)] = BETWEEN
    if allow_low_quality:
        best = iou.max(dim=1).values
        _, predictions = torch.where(iou == best[:, None])
        matches[predictions] = original[predictions]
    return matches


def sample_balanced(labels: Tensor, batch_size: int, positive_fraction: float,
                    generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    """At most ``batch_size`` predictions, at most ``positive_fraction`` of them positive (labels >= 1), the rest
    negative (labels == 0), each drawn uniformly; labels < 0 are never drawn.

    Returns:
        ``(positive indices, negative indices)`` int64.
    """
    positive = torch.where(labels >= 1)[0]
    negative = torch.where(labels == 0)[0]
    num_pos = min(int(batch_size * positive_fraction), positive.numel())
    num_neg = min(batch_size - num_pos, negative.numel())
    pick_pos = torch.randperm(positive.numel(), generator=generator)[:num_pos].to(labels.device)
    pick_neg = torch.randperm(negative.numel(), generator=generator)[:num_neg].to(labels.device)
    return positive[pick_pos], negative[pick_neg]
