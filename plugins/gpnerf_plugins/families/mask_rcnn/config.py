"""Options of the ``mask_rcnn`` family (``+experiment=baselines/mask_rcnn``, ``baselines/mask_rcnn_swin_t``):
Mask R-CNN's architecture at the sizes two CPU cores train, each official value (torchvision's
``maskrcnn_resnet50_fpn``) in the field's docstring (docs/families/mask_rcnn.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from gpnerf_core import ModelConfig


@dataclass
class MaskRCNNRates:
    """The family's learning-rate group (``model.lr.<group>``)."""

    detector: float = 1e-4
    """Every weight of the detector, from scratch with Adam (Mask R-CNN: SGD at 0.02, momentum 0.9, 16 images a
    step, from ImageNet weights)."""


@dataclass
class MaskRCNNLossWeights:
    """The weight of each of the detector's own loss terms (``model.loss_weights.<term>``, the terms of
    ``detector.LOSS_NAMES``): all 1, the plain sum torchvision and detectron2 train."""

    rpn_objectness: float = 1.0
    rpn_box: float = 1.0
    box_class: float = 1.0
    box_regression: float = 1.0
    mask: float = 1.0


@dataclass
class MaskRCNNConfig(ModelConfig):
    """Mask R-CNN (He et al., ICCV 2017) fitted on one scene's training frames and their instance masks, scoring the
    real RGB of its held-out frames: a 2D baseline that sees the true image (``Capabilities.segments_image``)."""

    name: str = "mask_rcnn"
    """Registry name of this model family."""
    num_source_views: int = 0
    """None: a 2D model reads only the target image."""
    backbone: str = "resnet34"
    """``resnet34`` (ResNet-34 with GroupNorm, from scratch; Mask R-CNN: ResNet-50 from ImageNet), ``swin_t`` (Swin-T:
    embedding 96, depths 2-2-6-2, heads 3-6-12-24, window 7) or ``resnet50`` (torchvision's, frozen BatchNorm: the
    backbone of its COCO checkpoint, ``+experiment=baselines/mask_rcnn_torchvision``)."""
    classes: int = 1
    """Object classes besides the background: 1, class-agnostic (the instance protocols score no classes); 90 for
    torchvision's COCO checkpoint."""
    min_size: int = 0
    """Resize every image so its shorter side is this many pixels (torchvision: 800; 0 keeps the frames' size)."""
    max_size: int = 1333
    """... unless its longer side would exceed this (torchvision: 1333)."""
    fpn_channels: int = 64
    """Channels of every FPN level and of the RPN (256)."""
    anchor_sizes: list[float] = field(default_factory=lambda: [8.0, 16.0, 32.0, 64.0, 128.0])
    """Anchor side in pixels on P2, P3, P4, P5, P6 (32 to 512 at torchvision's 800-pixel images; here 8 to 128 for
    96 x 128 frames). None may exceed the image's longer side."""
    aspect_ratios: list[float] = field(default_factory=lambda: [0.5, 1.0, 2.0])
    """Anchor height / width at every level (0.5, 1, 2)."""
    rpn_pre_nms_top_n: list[int] = field(default_factory=lambda: [1000, 500])
    """Best anchors kept per level before NMS, in training and at test time (2000, 1000)."""
    rpn_post_nms_top_n: list[int] = field(default_factory=lambda: [500, 250])
    """Proposals kept per image after NMS, in training and at test time (2000, 1000)."""
    rpn_batch_size_per_image: int = 256
    """Anchors sampled per image for the RPN's losses, half positive at most (256)."""
    roi_batch_size_per_image: int = 128
    """Proposals sampled per image for the box and mask losses, a quarter positive at most (512)."""
    box_hidden: int = 256
    """Width of the box head's two fully connected layers (1024)."""
    mask_hidden: int = 64
    """Width of the mask head's four convolutions and its transposed convolution (256)."""
    slots: int = 100
    """Detections kept per image (``box_detections_per_img``, 100): each is one instance slot of the scores the
    instance metrics read. A training frame with more instance ids than this is said once, naming this key."""
    score_threshold: float = 0.05
    """Detections below this class score are dropped (0.05)."""
    aligned: bool = True
    """RoIAlign shifts boxes by half a cell (detectron2's ROIAlignV2; torchvision's Mask R-CNN: False)."""
    drop_path: float = 0.2
    """Swin-T's stochastic-depth rate (its Mask R-CNN configs: 0.2); unused by ResNet-34."""
    lr: MaskRCNNRates = field(default_factory=MaskRCNNRates)
    """Learning rates (``model.lr.detector``)."""
    loss_weights: MaskRCNNLossWeights = field(default_factory=MaskRCNNLossWeights)
    """The weight of each loss term (``model.loss_weights.<term>``)."""

    runtime_keys: ClassVar[tuple[str, ...]] = ModelConfig.runtime_keys + ("score_threshold",)
