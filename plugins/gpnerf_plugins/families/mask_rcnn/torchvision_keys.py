"""torchvision's ``maskrcnn_resnet50_fpn`` state dict (a COCO checkpoint read from a local file, never downloaded)
onto this family's names, for ``model.init=<file>`` with ``model.backbone=resnet50``
(``+experiment=baselines/mask_rcnn_torchvision``).

torchvision's names changed once: its v2 modules wrap convs (``rpn.head.conv.0.0``, ``fpn.inner_blocks.0.0``,
``mask_head.0.0``) where v1 holds them bare (``rpn.head.conv``, ``fpn.inner_blocks.0``, ``mask_head.mask_fcn1``); both
are read.
"""

from __future__ import annotations

import re
from typing import Any, Mapping

from torch import Tensor

FORMAT = "torchvision_maskrcnn"
MARKERS = ("backbone.body.conv1.weight", "roi_heads.box_predictor.cls_score.weight")
"""Keys every torchvision Mask R-CNN checkpoint has."""


def is_torchvision(checkpoint: Mapping[str, Any]) -> bool:
    return all(key in checkpoint for key in MARKERS)


def candidates(own: str) -> tuple[str, ...]:
    """The torchvision keys (v2 first, then v1) that hold this family's state-dict key ``own``; none for a key
    torchvision has no counterpart of."""
    rules = (
        (r"detector\.backbone\.body\.(.+)", (r"backbone.body.\1",)),
        (r"detector\.backbone\.fpn\.lateral_convs\.(\d+)\.(\w+)",
         (r"backbone.fpn.inner_blocks.\1.0.\2", r"backbone.fpn.inner_blocks.\1.\2")),
        (r"detector\.backbone\.fpn\.fpn_convs\.(\d+)\.(\w+)",
         (r"backbone.fpn.layer_blocks.\1.0.\2", r"backbone.fpn.layer_blocks.\1.\2")),
        (r"detector\.rpn_head\.conv\.(\w+)", (r"rpn.head.conv.0.0.\1", r"rpn.head.conv.\1")),
        (r"detector\.rpn_head\.(cls_logits|bbox_pred)\.(\w+)", (r"rpn.head.\1.\2",)),
        (r"detector\.roi_heads\.box_head\.(fc6|fc7)\.(\w+)", (r"roi_heads.box_head.\1.\2",)),
        (r"detector\.roi_heads\.box_head\.(cls_score|bbox_pred)\.(\w+)", (r"roi_heads.box_predictor.\1.\2",)),
        (r"detector\.roi_heads\.mask_head\.deconv\.(\w+)", (r"roi_heads.mask_predictor.conv5_mask.\1",)),
        (r"detector\.roi_heads\.mask_head\.logits\.(\w+)", (r"roi_heads.mask_predictor.mask_fcn_logits.\1",)),
    )
    for pattern, targets in rules:
        found = re.fullmatch(pattern, own)
        if found:
            return tuple(found.expand(t) for t in targets)
    conv = re.fullmatch(r"detector\.roi_heads\.mask_head\.convs\.(\d+)\.(\w+)", own)
    if conv:  # convs.0, .2, .4, .6 (ReLUs between): mask_fcn1..4 (v1), mask_head.0..3.0 (v2)
        k = int(conv.group(1)) // 2
        return (f"roi_heads.mask_head.{k}.0.{conv.group(2)}", f"roi_heads.mask_head.mask_fcn{k + 1}.{conv.group(2)}")
    return ()


def map_torchvision(own_keys: list[str], checkpoint: Mapping[str, Tensor]) -> dict[str, tuple[str, Tensor]]:
    """``{own key: (torchvision key, tensor)}`` for every key of this family that the checkpoint holds; the core
    compares names and shapes and reports what is missing or left over."""
    mapped = {}
    for own in own_keys:
        for key in candidates(own):
            if key in checkpoint:
                mapped[own] = (key, checkpoint[key])
                break
    return mapped
