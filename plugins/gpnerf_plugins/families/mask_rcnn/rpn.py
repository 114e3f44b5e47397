"""The region proposal network over the FPN levels (Ren et al. 2015; Lin et al. 2017): torchvision's ``RPNHead`` and
``RegionProposalNetwork`` (proposal selection per level, NMS, the sampled objectness and box losses)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_plugins.families.mask_rcnn.boxes import BoxCoder, batched_nms, box_iou, clip_boxes, remove_small_boxes
from gpnerf_plugins.families.mask_rcnn.matching import BELOW_LOW, BETWEEN, match, sample_balanced


@dataclass(frozen=True)
class RPNSettings:
    """The RPN's numbers (torchvision's Mask R-CNN defaults in each comment; ``MaskRCNNConfig`` gives them)."""

    pre_nms_top_n: tuple[int, int]
    """Best-scored anchors kept per level before NMS, (training, testing) (2000, 1000)."""
    post_nms_top_n: tuple[int, int]
    """Proposals kept per image after NMS, (training, testing) (2000, 1000)."""
    nms_threshold: float = 0.7
    fg_iou: float = 0.7
    bg_iou: float = 0.3
    batch_size_per_image: int = 256
    positive_fraction: float = 0.5
    min_size: float = 1e-3


class RPNHead(nn.Module):
    """A shared 3x3 conv + ReLU, then per anchor an objectness logit and 4 box deltas (normal(0, 0.01) weights, zero
    biases, as torchvision).

    Args:
        channels: the FPN's channels; anchors: A anchors per cell.
    """

    def __init__(self, channels: int, anchors: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)
        self.cls_logits = nn.Conv2d(channels, anchors, 1)
        self.bbox_pred = nn.Conv2d(channels, anchors * 4, 1)
        for layer in (self.conv, self.cls_logits, self.bbox_pred):
            nn.init.normal_(layer.weight, std=0.01)
            nn.init.zeros_(layer.bias)

    def forward(self, levels: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
        """Levels ``[N, C, h, w]`` -> per level objectness ``[N, h * w * A]`` and deltas ``[N, h * w * A, 4]``, laid out
        as the anchors (``anchors.grid_anchors``)."""
        objectness, deltas = [], []
        for x in levels:
            t = F.relu(self.conv(x))
            n, _, h, w = x.shape
            objectness.append(self.cls_logits(t).permute(0, 2, 3, 1).reshape(n, -1))
            deltas.append(self.bbox_pred(t).reshape(n, -1, 4, h, w).permute(0, 3, 4, 1, 2).reshape(n, -1, 4))
        return objectness, deltas


def select_proposals(anchors: list[Tensor], objectness: list[Tensor], deltas: list[Tensor], coder: BoxCoder,
                     image_size: tuple[int, int], settings: RPNSettings, training: bool) -> list[Tensor]:
    """Each image's proposals ``[P, 4]`` (detached), best first: per level the ``pre_nms_top_n`` best anchors, decoded
    and clipped, tiny boxes removed, NMS within each level, then the ``post_nms_top_n`` best over all levels."""
    pre, post = settings.pre_nms_top_n[not training], settings.post_nms_top_n[not training]
    out = []
    for i in range(objectness[0].shape[0]):
        boxes, scores, groups = [], [], []
        for k, (a, o, d) in enumerate(zip(anchors, objectness, deltas)):
            o, d = o[i].detach(), d[i].detach()
            top = o.topk(min(pre, o.numel())).indices
            decoded = clip_boxes(coder.decode(d[top], a[top]), *image_size)
            boxes.append(decoded)
            scores.append(torch.sigmoid(o[top]))
            groups.append(torch.full((len(top),), k, dtype=torch.int64, device=o.device))
        boxes_i, scores_i, groups_i = torch.cat(boxes), torch.cat(scores), torch.cat(groups)
        keep = remove_small_boxes(boxes_i, settings.min_size)
        boxes_i, scores_i, groups_i = boxes_i[keep], scores_i[keep], groups_i[keep]
        keep = batched_nms(boxes_i, scores_i, groups_i, settings.nms_threshold)[:post]
        out.append(boxes_i[keep])
    return out


def rpn_losses(anchors: Tensor, objectness: Tensor, deltas: Tensor, gt_boxes: list[Tensor], coder: BoxCoder,
               settings: RPNSettings, generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    """The RPN's two losses over each image's sampled anchors.

    Args:
        anchors: ``[A, 4]`` all levels'; objectness: ``[N, A]``; deltas: ``[N, A, 4]``; gt_boxes: per image ``[G, 4]``.

    Returns:
        ``(objectness BCE averaged over the sampled anchors, smooth-L1 (beta 1/9) of the positives' deltas summed and
        divided by the sampled anchors)``, torchvision's normalisation.
    """
    labels, targets = [], []
    for boxes in gt_boxes:
        matches = match(box_iou(boxes, anchors), settings.fg_iou, settings.bg_iou, allow_low_quality=True)
        label = (matches >= 0).float()
        label[matches == BELOW_LOW] = 0.0
        label[matches == BETWEEN] = -1.0
        labels.append(label)
        targets.append(coder.encode(boxes[matches.clamp(min=0)], anchors))
    positives, negatives = [], []
    for i, label in enumerate(labels):
        pos, neg = sample_balanced(label, settings.batch_size_per_image, settings.positive_fraction, generator)
        offset = i * anchors.shape[0]
        positives.append(pos + offset)
        negatives.append(neg + offset)
    pos, neg = torch.cat(positives), torch.cat(negatives)
    sampled = torch.cat([pos, neg])
    flat_labels, flat_targets = torch.cat(labels), torch.cat(targets)
    box_loss = F.smooth_l1_loss(deltas.reshape(-1, 4)[pos], flat_targets[pos], beta=1 / 9, reduction="sum")
    box_loss = box_loss / max(1, sampled.numel())
    object_loss = F.binary_cross_entropy_with_logits(objectness.reshape(-1)[sampled], flat_labels[sampled])
    return object_loss, box_loss
