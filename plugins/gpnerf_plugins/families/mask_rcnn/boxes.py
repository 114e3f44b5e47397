"""Box arithmetic of the detector in plain torch: IoU, the box coder, clipping, non-maximum suppression.

Boxes are ``[N, 4]`` float ``(x1, y1, x2, y2)`` in pixels of the (unpadded) input image, x to the right, y down; a
pixel ``(u, v)`` covers ``[u, u + 1) x [v, v + 1)``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

BBOX_CLIP = math.log(1000.0 / 16)
"""Largest predicted log scale change of a box (torchvision's and detectron2's ``_DEFAULT_SCALE_CLAMP``)."""


def box_area(boxes: Tensor) -> Tensor:
    """``[N, 4]`` -> ``[N]`` areas in square pixels (0 for an empty box)."""
    return (boxes[:, 2] - boxes[:, 0]).clamp_min(0) * (boxes[:, 3] - boxes[:, 1]).clamp_min(0)


def box_iou(a: Tensor, b: Tensor) -> Tensor:
    """``[N, 4]``, ``[M, 4]`` -> ``[N, M]`` intersection over union (0 where the union is empty)."""
    top_left = torch.maximum(a[:, None, :2], b[None, :, :2])
    bottom_right = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (bottom_right - top_left).clamp_min(0).prod(dim=2)
    union = box_area(a)[:, None] + box_area(b)[None, :] - inter
    return torch.where(union > 0, inter / union.clamp_min(1e-12), torch.zeros_like(inter))


def clip_boxes(boxes: Tensor, height: int, width: int) -> Tensor:
    """Boxes clipped to the image ``[0, width] x [0, height]``."""
    x = boxes[..., 0::2].clamp(0, width)
    y = boxes[..., 1::2].clamp(0, height)
    return torch.stack([x[..., 0], y[..., 0], x[..., 1], y[..., 1]], dim=-1)


class BoxCoder:
    """R-CNN's box parameterisation (Girshick et al. 2014): ``(dx, dy, dw, dh)`` of a box relative to a reference,
    each multiplied by its weight (the RPN: 1, 1, 1, 1; the box head: 10, 10, 5, 5).

    Args:
        weights: ``(wx, wy, ww, wh)``.
    """

    def __init__(self, weights: tuple[float, float, float, float]) -> None:
        self.weights = weights

    def encode(self, boxes: Tensor, references: Tensor) -> Tensor:
        """``[N, 4]`` target boxes against ``[N, 4]`` references -> ``[N, 4]`` deltas."""
        wx, wy, ww, wh = self.weights
        ref_w, ref_h = references[:, 2] - references[:, 0], references[:, 3] - references[:, 1]
        ref_x, ref_y = references[:, 0] + 0.5 * ref_w, references[:, 1] + 0.5 * ref_h
        w, h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
        x, y = boxes[:, 0] + 0.5 * w, boxes[:, 1] + 0.5 * h
        return torch.stack([wx * (x - ref_x) / ref_w, wy * (y - ref_y) / ref_h,
                            ww * torch.log(w / ref_w), wh * torch.log(h / ref_h)], dim=1)

    def decode(self, deltas: Tensor, references: Tensor) -> Tensor:
        """``[N, 4 * C]`` deltas (C boxes per reference) on ``[N, 4]`` references -> ``[N, 4 * C]`` boxes."""
        wx, wy, ww, wh = self.weights
        ref_w, ref_h = references[:, 2:3] - references[:, 0:1], references[:, 3:4] - references[:, 1:2]
        ref_x, ref_y = references[:, 0:1] + 0.5 * ref_w, references[:, 1:2] + 0.5 * ref_h
        dx, dy = deltas[:, 0::4] / wx, deltas[:, 1::4] / wy
        dw = (deltas[:, 2::4] / ww).clamp(max=BBOX_CLIP)
        dh = (deltas[:, 3::4] / wh).clamp(max=BBOX_CLIP)
        x, y = dx * ref_w + ref_x, dy * ref_h + ref_y
        w, h = torch.exp(dw) * ref_w, torch.exp(dh) * ref_h
        boxes = torch.stack([x - 0.5 * w, y - 0.5 * h, x + 0.5 * w, y + 0.5 * h], dim=2)
        return boxes.reshape(deltas.shape[0], -1)


def nms(boxes: Tensor, scores: Tensor, threshold: float) -> Tensor:
    """Greedy non-maximum suppression: visit boxes by decreasing score, keep a box unless it overlaps a kept one by
    IoU > ``threshold``.

    Args:
        boxes: ``[N, 4]``; scores: ``[N]``.

    Returns:
        ``[M]`` int64 indices of the kept boxes, by decreasing score (ties in index order, as a stable sort gives).
    """
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.int64, device=boxes.device)
    order = torch.sort(scores, descending=True, stable=True).indices
    overlaps = box_iou(boxes[order], boxes[order]) > threshold
    suppressed = torch.zeros(len(order), dtype=torch.bool)
    rows = overlaps.cpu()
    keep = []
    for i in range(len(order)):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= rows[i]
    return order[torch.tensor(keep, dtype=torch.int64, device=boxes.device)]


def batched_nms(boxes: Tensor, scores: Tensor, groups: Tensor, threshold: float) -> Tensor:
    """``nms`` within each group (a class, an FPN level) independently: each group's boxes are shifted apart by more
    than the largest coordinate so that boxes of different groups never overlap. Returns kept indices by decreasing
    score."""
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.int64, device=boxes.device)
    offsets = groups.to(boxes) * (boxes.max() + 1)
    return nms(boxes + offsets[:, None], scores, threshold)


def remove_small_boxes(boxes: Tensor, min_size: float) -> Tensor:
    """Indices of the boxes whose width and height are both at least ``min_size`` pixels."""
    w, h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
    return torch.where((w >= min_size) & (h >= min_size))[0]
