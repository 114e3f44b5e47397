"""Mask R-CNN's second stage (He et al. 2017): the box head on 7x7 RoIAlign features, the mask head on 14x14 ones
predicting 28x28 masks, their training targets and losses, and the detections at test time (torchvision's
``RoIHeads``, ``TwoMLPHead``, ``FastRCNNPredictor``, ``MaskRCNNHeads``, ``MaskRCNNPredictor``)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_plugins.families.mask_rcnn.boxes import BoxCoder, batched_nms, box_iou, clip_boxes, remove_small_boxes
from gpnerf_plugins.families.mask_rcnn.matching import match, sample_balanced
from gpnerf_plugins.families.mask_rcnn.roi_align import multiscale_roi_align, roi_align
from gpnerf_plugins.families.mask_rcnn.targets import InstanceTargets


@dataclass(frozen=True)
class RoISettings:
    """The second stage's numbers (torchvision's defaults in each comment; ``MaskRCNNConfig`` gives them)."""

    batch_size_per_image: int
    """Proposals sampled per image for the box loss (512)."""
    detections_per_image: int
    """Detections kept per image (100)."""
    positive_fraction: float = 0.25
    fg_iou: float = 0.5
    bg_iou: float = 0.5
    score_threshold: float = 0.05
    nms_threshold: float = 0.5
    sampling_ratio: int = 2
    aligned: bool = True
    box_pool: int = 7
    mask_pool: int = 14


class BoxHead(nn.Module):
    """Two fully connected layers with ReLU on the flattened pooled features, then class scores (background first)
    and class-specific box deltas.

    Args:
        channels: pooled feature channels; pool: its side; hidden: the layers' width (1024); classes: C object classes.
    """

    def __init__(self, channels: int, pool: int, hidden: int, classes: int) -> None:
        super().__init__()
        self.fc6 = nn.Linear(channels * pool * pool, hidden)
        self.fc7 = nn.Linear(hidden, hidden)
        self.cls_score = nn.Linear(hidden, classes + 1)
        self.bbox_pred = nn.Linear(hidden, (classes + 1) * 4)

    def forward(self, pooled: Tensor) -> tuple[Tensor, Tensor]:
        """``[R, C, p, p]`` -> class logits ``[R, C + 1]`` and deltas ``[R, (C + 1) * 4]``."""
        x = F.relu(self.fc7(F.relu(self.fc6(pooled.flatten(1)))))
        return self.cls_score(x), self.bbox_pred(x)


class MaskHead(nn.Module):
    """Four 3x3 convs with ReLU, a 2x2 stride-2 transposed conv with ReLU, a 1x1 conv to one mask logit map per class
    (Kaiming-normal fan-out weights, zero biases, as torchvision).

    Args:
        channels: pooled feature channels; hidden: the convs' width (256); classes: C object classes.
    """

    def __init__(self, channels: int, hidden: int, classes: int) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        for i in range(4):
            layers += [nn.Conv2d(channels if i == 0 else hidden, hidden, 3, padding=1), nn.ReLU()]
        self.convs = nn.Sequential(*layers)
        self.deconv = nn.ConvTranspose2d(hidden, hidden, 2, stride=2)
        self.logits = nn.Conv2d(hidden, classes + 1, 1)
        for module in self.modules():
            if isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
                nn.init.zeros_(module.bias)

    def forward(self, pooled: Tensor) -> Tensor:
        """``[R, C, p, p]`` -> ``[R, C + 1, 2p, 2p]`` mask logits."""
        return self.logits(F.relu(self.deconv(self.convs(pooled))))


@dataclass(frozen=True)
class Detections:
    """One image's detections, best first: ``boxes [D, 4]``, ``scores [D]``, ``labels [D]``, ``masks [D, M, M]``
    probabilities in their boxes."""

    boxes: Tensor
    scores: Tensor
    labels: Tensor
    masks: Tensor


def _rois(boxes: list[Tensor]) -> Tensor:
    """Per-image ``[P_i, 4]`` boxes -> ``[sum P_i, 5]`` with the image index first."""
    return torch.cat([torch.cat([torch.full_like(b[:, :1], i), b], dim=1) for i, b in enumerate(boxes)])


class RoIHeads(nn.Module):
    """The box and mask heads over FPN levels P2-P5.

    Args:
        channels: the FPN's channels; box_hidden, mask_hidden: the heads' widths; classes: C object classes;
        settings: ``RoISettings``.
    """

    def __init__(self, channels: int, box_hidden: int, mask_hidden: int, classes: int, settings: RoISettings) -> None:
        super().__init__()
        self.settings = settings
        self.box_head = BoxHead(channels, settings.box_pool, box_hidden, classes)
        self.mask_head = MaskHead(channels, mask_hidden, classes)
        self.coder = BoxCoder((10.0, 10.0, 5.0, 5.0))

    def _pool(self, levels: list[Tensor], strides: list[int], rois: Tensor, size: int) -> Tensor:
        s = self.settings
        return multiscale_roi_align(levels, strides, rois, size, s.sampling_ratio, s.aligned)

    def _sample(self, proposals: list[Tensor], targets: list[InstanceTargets],
                generator: torch.Generator | None) -> tuple[list[Tensor], list[Tensor], list[Tensor]]:
        """Per image, the sampled proposals ``[S, 4]`` (the GT boxes added to the candidates), their class labels
        ``[S]`` (0: background) and the index of their matched GT box ``[S]`` (meaningless where the label is 0)."""
        s = self.settings
        sampled, labels, matched = [], [], []
        for props, target in zip(proposals, targets):
            props = torch.cat([props, target.boxes])
            matches = match(box_iou(target.boxes, props), s.fg_iou, s.bg_iou, allow_low_quality=False)
            label = target.labels[matches.clamp(min=0)].clone()
            label[matches < 0] = 0
            pos, neg = sample_balanced(label, s.batch_size_per_image, s.positive_fraction, generator)
            keep = torch.cat([pos, neg])
            sampled.append(props[keep])
            labels.append(label[keep])
            matched.append(matches.clamp(min=0)[keep])
        return sampled, labels, matched

    def losses(self, levels: list[Tensor], strides: list[int], proposals: list[Tensor], targets: list[InstanceTargets],
               generator: torch.Generator | None) -> dict[str, Tensor]:
        """The box head's classification CE and box smooth-L1 (beta 1/9, summed over the positives and divided by the
        sampled proposals) and the mask BCE on each positive's own class channel against its ground-truth mask cut
        out by RoIAlign at 28 x 28 (torchvision's ``project_masks_on_boxes``), over proposals sampled per image
        (``_sample``).

        Args:
            levels: FPN maps P2-P6 ``[N, C, h, w]`` at ``strides``; proposals: per image ``[P, 4]`` (detached);
                targets: per image.
        """
        s = self.settings
        sampled, labels, matched = self._sample(proposals, targets, generator)
        rois = _rois(sampled)
        class_logits, deltas = self.box_head(self._pool(levels[:4], strides[:4], rois, s.box_pool))
        label = torch.cat(labels)
        positive = torch.where(label > 0)[0]
        box_targets = torch.cat([self.coder.encode(t.boxes[m], b) for t, m, b in zip(targets, matched, sampled)])
        cls_loss = F.cross_entropy(class_logits, label)
        deltas = deltas.reshape(deltas.shape[0], -1, 4)[positive, label[positive]]
        box_loss = F.smooth_l1_loss(deltas, box_targets[positive], beta=1 / 9, reduction="sum") / max(1, label.numel())
        mask_logits = self.mask_head(self._pool(levels[:4], strides[:4], rois[positive], s.mask_pool))
        size = mask_logits.shape[-1]
        cut = []  # each positive's GT mask inside its proposal, at the mask head's size
        for gt, lab, boxes, target in zip(matched, labels, sampled, targets):
            own = torch.where(lab > 0)[0]
            cut_rois = torch.cat([gt[own, None].to(boxes), boxes[own]], dim=1)
            cut.append(roi_align(target.masks[:, None], cut_rois, size, 1.0, s.sampling_ratio, s.aligned)[:, 0])
        if positive.numel():
            mask_loss = F.binary_cross_entropy_with_logits(
                mask_logits[torch.arange(positive.numel()), label[positive]], torch.cat(cut))
        else:
            mask_loss = mask_logits.sum() * 0
        return {"box_class": cls_loss, "box_regression": box_loss, "mask": mask_loss}

    def detect(self, levels: list[Tensor], strides: list[int], proposals: list[Tensor],
               image_size: tuple[int, int]) -> list[Detections]:
        """Each image's detections: class-specific boxes decoded and clipped, background dropped, scores above
        ``score_threshold``, tiny boxes removed, NMS per class, the ``detections_per_image`` best, and their masks'
        probabilities in the predicted class's channel (differentiable in the heads' weights; ``predict`` runs it under
        inference mode)."""
        s = self.settings
        class_logits, deltas = self.box_head(self._pool(levels[:4], strides[:4], _rois(proposals), s.box_pool))
        scores_all = F.softmax(class_logits, dim=1)
        boxes_all = self.coder.decode(deltas, torch.cat(proposals))
        out, start = [], 0
        for props in proposals:
            end = start + len(props)
            scores, boxes = scores_all[start:end, 1:], boxes_all[start:end].reshape(-1, scores_all.shape[1], 4)[:, 1:]
            start = end
            classes = scores.shape[1]
            boxes = clip_boxes(boxes, *image_size).reshape(-1, 4)
            labels = torch.arange(1, classes + 1, device=boxes.device).repeat(len(props))
            scores = scores.reshape(-1)
            keep = torch.where(scores > s.score_threshold)[0]
            boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
            keep = remove_small_boxes(boxes, 1e-2)
            boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
            keep = batched_nms(boxes, scores, labels, s.nms_threshold)[: s.detections_per_image]
            out.append(Detections(boxes[keep], scores[keep], labels[keep], boxes.new_zeros(0)))
        rois = _rois([d.boxes for d in out])
        mask_logits = self.mask_head(self._pool(levels[:4], strides[:4], rois, s.mask_pool))
        labels = torch.cat([d.labels for d in out])
        probs = torch.sigmoid(mask_logits[torch.arange(len(labels)), labels])
        result, start = [], 0
        for d in out:
            end = start + len(d.boxes)
            result.append(Detections(d.boxes, d.scores, d.labels, probs[start:end]))
            start = end
        return result
