"""Mask R-CNN (He et al., ICCV 2017) assembled: normalisation and padding, backbone + FPN, RPN, RoI heads
(torchvision's ``GeneralizedRCNN`` / ``MaskRCNN`` data flow, without its resizing: the frames keep their size)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_plugins.families.mask_rcnn.anchors import pyramid_anchors
from gpnerf_plugins.families.mask_rcnn.backbones import BackboneFPN
from gpnerf_plugins.families.mask_rcnn.boxes import BoxCoder
from gpnerf_plugins.families.mask_rcnn.roi_heads import Detections, RoIHeads, RoISettings
from gpnerf_plugins.families.mask_rcnn.rpn import RPNHead, RPNSettings, rpn_losses, select_proposals
from gpnerf_plugins.families.mask_rcnn.targets import InstanceTargets

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
SIZE_DIVISIBLE = 32
"""Inputs are padded (bottom, right) to a multiple of this (torchvision's ``size_divisible``)."""
LOSS_NAMES = ("rpn_objectness", "rpn_box", "box_class", "box_regression", "mask")
"""The five loss terms, in the order of the two stages."""


@dataclass(frozen=True)
class DetectorSettings:
    """What ``MaskRCNN`` is built with (``MaskRCNNConfig`` gives each, with torchvision's value)."""

    backbone: str
    fpn_channels: int
    anchor_sizes: tuple[float, ...]
    aspect_ratios: tuple[float, ...]
    rpn: RPNSettings
    roi: RoISettings
    box_hidden: int
    mask_hidden: int
    classes: int = 1
    drop_path: float = 0.2
    min_size: int = 0
    """Images are resized so that their shorter side is ``min_size`` (torchvision: 800), unless the longer would exceed
    ``max_size`` (1333); 0 keeps the frames' size. Detections are scaled back to the frame."""
    max_size: int = 1333


class MaskRCNN(nn.Module):
    """Mask R-CNN on whole images: ``losses`` in training, ``detect`` at test time.

    Args:
        settings: ``DetectorSettings``.
    """

    def __init__(self, settings: DetectorSettings) -> None:
        super().__init__()
        self.settings = settings
        self.backbone = BackboneFPN(settings.backbone, settings.fpn_channels, settings.drop_path)
        self.rpn_head = RPNHead(settings.fpn_channels, len(settings.aspect_ratios))
        self.roi_heads = RoIHeads(settings.fpn_channels, settings.box_hidden, settings.mask_hidden, settings.classes,
                                  settings.roi)
        self.rpn_coder = BoxCoder((1.0, 1.0, 1.0, 1.0))
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def _resized(self, images: Tensor) -> tuple[Tensor, tuple[float, float]]:
        """``images`` resized as torchvision's ``GeneralizedRCNNTransform`` (bilinear), and the (y, x) ratios of the
        resized to the original size; unchanged with ``min_size`` 0."""
        if not self.settings.min_size:
            return images, (1.0, 1.0)
        height, width = images.shape[-2:]
        scale = min(self.settings.min_size / min(height, width), self.settings.max_size / max(height, width))
        resized = F.interpolate(images, scale_factor=scale, mode="bilinear", align_corners=False,
                                recompute_scale_factor=True)
        return resized, (resized.shape[-2] / height, resized.shape[-1] / width)

    def _features(self, images: Tensor) -> tuple[list[Tensor], list[Tensor], list[Tensor], list[Tensor]]:
        """``[N, 3, H, W]`` in [0, 1] -> FPN levels, the anchors of each level, RPN objectness and deltas per level."""
        height, width = images.shape[-2:]
        x = (images - self.mean) / self.std
        x = F.pad(x, (0, (-width) % SIZE_DIVISIBLE, 0, (-height) % SIZE_DIVISIBLE))
        levels = self.backbone(x)
        grids = [tuple(level.shape[-2:]) for level in levels]
        anchors = pyramid_anchors(list(self.settings.anchor_sizes), list(self.settings.aspect_ratios), grids,
                                  tuple(x.shape[-2:]))
        objectness, deltas = self.rpn_head(levels)
        return levels, [a.to(x.device) for a in anchors], objectness, deltas

    def losses(self, images: Tensor, targets: list[InstanceTargets],
               generator: torch.Generator | None = None) -> dict[str, Tensor]:
        """The five unweighted loss terms (``LOSS_NAMES``) of images ``[N, 3, H, W]`` in [0, 1] and their targets;
        ``generator`` draws the sampled anchors and proposals."""
        images, (ry, rx) = self._resized(images)
        if (ry, rx) != (1.0, 1.0):  # the targets follow the image (masks: nearest, as torchvision)
            scale = torch.tensor([rx, ry, rx, ry], device=images.device)
            targets = [InstanceTargets(t.boxes * scale, t.labels, F.interpolate(t.masks[:, None],
                       size=images.shape[-2:], mode="nearest")[:, 0]) for t in targets]
        size = (images.shape[-2], images.shape[-1])
        levels, anchors, objectness, deltas = self._features(images)
        proposals = select_proposals(anchors, objectness, deltas, self.rpn_coder, size, self.settings.rpn, True)
        rpn_obj, rpn_box = rpn_losses(torch.cat(anchors), torch.cat(objectness, dim=1), torch.cat(deltas, dim=1),
                                      [t.boxes for t in targets], self.rpn_coder, self.settings.rpn, generator)
        second = self.roi_heads.losses(levels, self.backbone.strides, proposals, targets, generator)
        return {"rpn_objectness": rpn_obj, "rpn_box": rpn_box, **second}

    def detect(self, images: Tensor) -> list[Detections]:
        """Each image's detections (``Detections``: at most ``detections_per_image``, best first; boxes in the
        pixels of ``images``)."""
        images, (ry, rx) = self._resized(images)
        size = (images.shape[-2], images.shape[-1])
        levels, anchors, objectness, deltas = self._features(images)
        proposals = select_proposals(anchors, objectness, deltas, self.rpn_coder, size, self.settings.rpn, False)
        found = self.roi_heads.detect(levels, self.backbone.strides, proposals, size)
        if (ry, rx) == (1.0, 1.0):
            return found
        scale = torch.tensor([1 / rx, 1 / ry, 1 / rx, 1 / ry], device=images.device)
        return [Detections(d.boxes * scale, d.scores, d.labels, d.masks) for d in found]
