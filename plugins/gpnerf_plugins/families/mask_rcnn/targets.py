"""Between instance-id images and the detector: ground-truth boxes and masks from ids, and detections pasted back into
per-pixel slot scores for the project's instance metrics."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor


@dataclass(frozen=True)
class InstanceTargets:
    """One image's ground truth for the detector.

    Attributes:
        boxes: ``[G, 4]`` tight boxes ``(x1, y1, x2, y2)`` in pixels, ``x2 = last column + 1`` (detectron2's
            ``BitMasks.get_bounding_boxes``).
        labels: ``[G]`` int64 classes in ``[1, C]`` (0 is the detector's background).
        masks: ``[G, H, W]`` float 0/1.
    """

    boxes: Tensor
    labels: Tensor
    masks: Tensor


def targets_from_ids(ids: Tensor) -> InstanceTargets:
    """Every instance id present in ``[H, W]`` ``ids`` is one ground-truth object of class 1 (class-agnostic, as the
    instance protocols score; the "background" id is one too, as the protocols count it), ids in increasing order."""
    values = torch.unique(ids)
    masks = ids[None] == values[:, None, None]  # [G, H, W]
    rows, cols = masks.any(dim=2), masks.any(dim=1)  # [G, H], [G, W]
    arange_h = torch.arange(ids.shape[0], device=ids.device)
    arange_w = torch.arange(ids.shape[1], device=ids.device)
    y1 = torch.where(rows, arange_h, ids.shape[0]).min(dim=1).values
    y2 = torch.where(rows, arange_h, -1).max(dim=1).values + 1
    x1 = torch.where(cols, arange_w, ids.shape[1]).min(dim=1).values
    x2 = torch.where(cols, arange_w, -1).max(dim=1).values + 1
    boxes = torch.stack([x1, y1, x2, y2], dim=1).float()
    labels = torch.ones(len(values), dtype=torch.int64, device=ids.device)
    return InstanceTargets(boxes=boxes, labels=labels, masks=masks.float())


def paste_masks(masks: Tensor, boxes: Tensor, height: int, width: int) -> Tensor:
    """``[D, M, M]`` mask probabilities in their ``[D, 4]`` boxes -> ``[D, H, W]`` probabilities on the image, 0 outside
    each box (detectron2's ``paste_masks_in_image``: every pixel centre inside a box samples the box's mask
    bilinearly)."""
    if masks.shape[0] == 0:
        return masks.new_zeros(0, height, width)
    ys = torch.arange(height, device=masks.device, dtype=masks.dtype) + 0.5
    xs = torch.arange(width, device=masks.device, dtype=masks.dtype) + 0.5
    x0, y0, x1, y1 = (boxes[:, i:i + 1] for i in range(4))
    gy = (ys[None] - y0) / (y1 - y0).clamp_min(1e-6) * 2 - 1  # [D, H]
    gx = (xs[None] - x0) / (x1 - x0).clamp_min(1e-6) * 2 - 1  # [D, W]
    grid = torch.stack([gx[:, None, :].expand(-1, height, -1), gy[:, :, None].expand(-1, -1, width)], dim=3)
    return F.grid_sample(masks[:, None], grid, align_corners=False)[:, 0]


def slot_logits(masks: Tensor, scores: Tensor, slots: int) -> Tensor:
    """Detections as the instance models' per-pixel slot scores (``slot_activation="sigmoid"``).

    Args:
        masks: ``[D, H, W]`` pasted mask probabilities of D <= ``slots`` detections; scores: ``[D]`` in [0, 1].

    Returns:
        ``[1, slots + 1, H, W]`` logits whose sigmoid is ``score * mask probability`` in detection d's slot, about 0 in
        the slots of no detection and the last ("no instance") channel: a pixel goes to the detection most confident
        of it, and a slot's confidence (the median of its pixels' values) follows its detection's score.
    """
    height, width = masks.shape[-2:]
    probability = masks.new_zeros(slots + 1, height, width)
    probability[: masks.shape[0]] = scores[:, None, None] * masks
    probability = probability.clamp(1e-6, 1 - 1e-6)
    return torch.log(probability / (1 - probability))[None]
