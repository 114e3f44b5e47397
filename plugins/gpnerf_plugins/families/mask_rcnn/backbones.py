"""The detector's backbone: ResNet-34 (the project's own ``BasicBlock``: InstanceNorm, reflect padding) or Swin-T
(``swin.py``), each with an FPN (the project's ``FPN``: 1x1 laterals, top-down nearest-upsample-and-add, 3x3 outputs)
and a max-pooled P6 for the RPN (torchvision's ``LastLevelMaxPool``)."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from gpnerf_core import ConfigError
from gpnerf_plugins.extractors.fpn import FPN
from gpnerf_plugins.extractors.resunet import BasicBlock
from gpnerf_plugins.families.mask_rcnn.swin import SwinTransformer

RESNET34_BLOCKS = (3, 4, 6, 3)
RESNET34_WIDTHS = (64, 128, 256, 512)
STRIDES = (4, 8, 16, 32, 64)
"""Pixels per cell of P2, P3, P4, P5 and P6."""


class ResNet34(nn.Module):
    """ResNet-34's four stages (3, 4, 6, 3 basic blocks of 64, 128, 256, 512 channels) after a 7x7 stride-2 stem; as
    in the project's extractor, the stride-2 step into stage 1 is its first block's (no max-pool).

    Returns C2-C5 at strides 4, 8, 16, 32 (``channels``)."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False, padding_mode="reflect")
        self.bn1 = nn.InstanceNorm2d(64, affine=True)
        stages, previous = [], 64
        for blocks, width in zip(RESNET34_BLOCKS, RESNET34_WIDTHS):
            stages.append(nn.Sequential(BasicBlock(previous, width, stride=2),
                                        *(BasicBlock(width, width) for _ in range(1, blocks))))
            previous = width
        self.stages = nn.ModuleList(stages)
        self.channels = list(RESNET34_WIDTHS)

    def forward(self, images: Tensor) -> list[Tensor]:
        """``[N, 3, H, W]`` (H, W multiples of 32) -> C2..C5 ``[N, c_k, H / 2^(k+2), W / 2^(k+2)]``."""
        x = F.relu(self.bn1(self.conv1(images)))
        taps = []
        for stage in self.stages:
            x = stage(x)
            taps.append(x)
        return taps


class BackboneFPN(nn.Module):
    """A backbone's C2-C5 through an FPN, plus P6 = max-pool(P5, 1, stride 2).

    Args:
        backbone: ``resnet34`` or ``swin_t``; channels: the FPN's (256 in Mask R-CNN); drop_path: Swin-T's
            stochastic depth rate.
    """

    def __init__(self, backbone: str, channels: int, drop_path: float) -> None:
        super().__init__()
        if backbone == "resnet34":
            self.body: nn.Module = ResNet34()
        elif backbone == "swin_t":
            self.body = SwinTransformer(drop_path=drop_path)
        else:
            raise ConfigError(f"model.backbone={backbone!r}: expected resnet34 or swin_t")
        self.fpn = FPN(self.body.channels, channels)
        self.strides = list(STRIDES)

    def forward(self, images: Tensor) -> list[Tensor]:
        """``[N, 3, H, W]`` -> P2..P6 ``[N, channels, H / s, W / s]`` for ``s`` in ``strides``."""
        levels = self.fpn(self.body(images))
        return levels + [F.max_pool2d(levels[-1], 1, 2)]
