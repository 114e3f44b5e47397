"""Building the ``mask_rcnn`` family from its options: it builds no parts (no extractor, no head)."""

from __future__ import annotations

from gpnerf_core import ConfigError, ModelParts
from gpnerf_plugins.families.mask_rcnn.config import MaskRCNNConfig
from gpnerf_plugins.families.mask_rcnn.detector import DetectorSettings
from gpnerf_plugins.families.mask_rcnn.model import MaskRCNNFamily
from gpnerf_plugins.families.mask_rcnn.roi_heads import RoISettings
from gpnerf_plugins.families.mask_rcnn.rpn import RPNSettings

C = MaskRCNNConfig


def _pair(key: str, values: list[int]) -> tuple[int, int]:
    if len(values) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in values):
        raise ConfigError(f"model.{key}={list(values)}: expected [training, testing], two integers >= 1")
    return int(values[0]), int(values[1])


def _positive(key: str, value: int | float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0:
        raise ConfigError(f"model.{key}={value!r}: expected a number > 0")


def build_mask_rcnn(*, parts: ModelParts, backbone: str = C.backbone, fpn_channels: int = C.fpn_channels,
                    anchor_sizes: list[float] | None = None, aspect_ratios: list[float] | None = None,
                    rpn_pre_nms_top_n: list[int] | None = None, rpn_post_nms_top_n: list[int] | None = None,
                    rpn_batch_size_per_image: int = C.rpn_batch_size_per_image,
                    roi_batch_size_per_image: int = C.roi_batch_size_per_image, box_hidden: int = C.box_hidden,
                    mask_hidden: int = C.mask_hidden, slots: int = C.slots, score_threshold: float = C.score_threshold,
                    aligned: bool = C.aligned, drop_path: float = C.drop_path, classes: int = C.classes,
                    min_size: int = C.min_size, max_size: int = C.max_size) -> MaskRCNNFamily:
    """Mask R-CNN from ``MaskRCNNConfig``'s fields (the list fields default to the config's); a configured ``+head``
    is refused (the detector's mask head makes its masks)."""
    if parts.configured("head"):
        raise ConfigError(f"model=mask_rcnn predicts its masks with its own mask head and decodes no feature map: drop "
                          f"+head={parts.name('head')}")
    defaults = C()
    anchor_sizes = list(anchor_sizes if anchor_sizes is not None else defaults.anchor_sizes)
    aspect_ratios = list(aspect_ratios if aspect_ratios is not None else defaults.aspect_ratios)
    if len(anchor_sizes) != 5:
        raise ConfigError(f"model.anchor_sizes={anchor_sizes}: expected 5 sizes, one for each of P2-P6")
    for key, values in (("anchor_sizes", anchor_sizes), ("aspect_ratios", aspect_ratios)):
        for value in values:
            _positive(key, value)
    for key, value in (("fpn_channels", fpn_channels), ("rpn_batch_size_per_image", rpn_batch_size_per_image),
                       ("roi_batch_size_per_image", roi_batch_size_per_image), ("box_hidden", box_hidden),
                       ("mask_hidden", mask_hidden), ("slots", slots), ("classes", classes),
                       ("max_size", max_size)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"model.{key}={value!r}: expected an integer >= 1")
    if isinstance(min_size, bool) or not isinstance(min_size, int) or min_size < 0:
        raise ConfigError(f"model.min_size={min_size!r}: expected 0 (no resizing) or a shorter side in pixels")
    if not 0.0 <= score_threshold < 1.0:
        raise ConfigError(f"model.score_threshold={score_threshold!r}: expected a class score in [0, 1)")
    rpn = RPNSettings(pre_nms_top_n=_pair("rpn_pre_nms_top_n", list(rpn_pre_nms_top_n or defaults.rpn_pre_nms_top_n)),
                      post_nms_top_n=_pair("rpn_post_nms_top_n",
                                           list(rpn_post_nms_top_n or defaults.rpn_post_nms_top_n)),
                      batch_size_per_image=rpn_batch_size_per_image)
    roi = RoISettings(batch_size_per_image=roi_batch_size_per_image, detections_per_image=slots,
                      score_threshold=float(score_threshold), aligned=bool(aligned))
    settings = DetectorSettings(backbone=backbone, fpn_channels=fpn_channels, anchor_sizes=tuple(anchor_sizes),
                                aspect_ratios=tuple(aspect_ratios), rpn=rpn, roi=roi, box_hidden=box_hidden,
                                mask_hidden=mask_hidden, classes=classes, drop_path=float(drop_path),
                                min_size=min_size, max_size=max_size)
    return MaskRCNNFamily(settings=settings)
